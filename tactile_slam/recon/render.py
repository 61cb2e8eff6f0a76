"""Offscreen PNG rendering of a mesh or an oriented point cloud from several views.

Matplotlib's Agg canvas draws Lambert-shaded triangles or points (Open3D's offscreen
renderer needs EGL/Vulkan, which headless machines often lack: it fails on this
project's machines). Large inputs are decimated first so a render stays within a few
seconds. Inputs are metres; axes are labelled in millimetres.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from mpl_toolkits.mplot3d.art3d import Poly3DCollection

from tactile_slam.recon.mesh import MeshError, TriMesh

VIEWS = ((30.0, -60.0), (30.0, 30.0), (30.0, 120.0), (-60.0, 210.0))  # (elevation, azimuth) degrees


def _shade(normals: np.ndarray, elev: float, azim: float) -> np.ndarray:
    """RGBA colours ``(N, 4)``: Lambert shading with the light at the camera."""
    e, a = np.radians(elev), np.radians(azim)
    light = np.array([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)])
    s = 0.25 + 0.75 * np.clip(normals @ light, 0.0, 1.0)
    return np.stack([s * 0.85, s * 0.75, s * 0.6, np.ones_like(s)], axis=1)


def _draw(points_mm: np.ndarray, draw: Callable, path: str | Path, views, size_px: int) -> Path:
    centre = (points_mm.max(0) + points_mm.min(0)) / 2
    half = (points_mm.max(0) - points_mm.min(0)).max() / 2 * 1.05 + 1e-9
    cols = int(np.ceil(np.sqrt(len(views))))
    rows = int(np.ceil(len(views) / cols))
    fig = Figure(figsize=(size_px / 100, size_px / 100 * rows / cols), dpi=100)
    FigureCanvasAgg(fig)
    for k, (elev, azim) in enumerate(views):
        ax = fig.add_subplot(rows, cols, k + 1, projection="3d")
        draw(ax, elev, azim)
        for axis, c in zip("xyz", centre):
            getattr(ax, f"set_{axis}lim")(c - half, c + half)
        ax.set_box_aspect((1, 1, 1))
        ax.view_init(elev=elev, azim=azim)
        for axis in "xyz":
            getattr(ax, f"set_{axis}label")(f"{axis} (mm)", fontsize=7)
        ax.set_title(f"elev {elev:.0f}, azim {azim:.0f}", fontsize=8)
        ax.tick_params(labelsize=6)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    return path


def render_views(mesh: TriMesh, path: str | Path, views=VIEWS, max_faces: int = 20000, size_px: int = 1000) -> Path:
    """Render a mesh (metres) from each ``(elevation, azimuth)`` into one PNG grid."""
    if mesh.n_faces == 0:
        raise MeshError("cannot render a mesh without faces")
    m = mesh.to_open3d()
    if len(m.triangles) > max_faces:
        m = m.simplify_quadric_decimation(max_faces)
    m.compute_triangle_normals()
    v = np.asarray(m.vertices) * 1000.0
    tris = v[np.asarray(m.triangles)]
    fn = np.asarray(m.triangle_normals)

    def draw(ax, elev, azim):
        ax.add_collection3d(Poly3DCollection(tris, facecolors=_shade(fn, elev, azim), edgecolors="none"))

    return _draw(v, draw, path, views, size_px)


def render_points(points: np.ndarray, normals: np.ndarray, path: str | Path, views=VIEWS,
                  max_points: int = 60000, size_px: int = 1000) -> Path:
    """Render ``(N, 3)`` points (metres) with ``(N, 3)`` outward normals into one PNG grid."""
    if len(points) == 0:
        raise MeshError("cannot render an empty point cloud")
    step = max(1, int(np.ceil(len(points) / max_points)))
    p = np.asarray(points)[::step] * 1000.0
    n = np.asarray(normals)[::step]

    def draw(ax, elev, azim):
        ax.scatter(p[:, 0], p[:, 1], p[:, 2], c=_shade(n, elev, azim), s=1.0, linewidths=0, depthshade=False)

    return _draw(p, draw, path, views, size_px)
