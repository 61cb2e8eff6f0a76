"""Offscreen PNG rendering of a mesh from several views (no display needed).

Matplotlib's Agg canvas draws Lambert-shaded triangles (Open3D's offscreen renderer
needs EGL/Vulkan, which headless machines often lack). Large meshes are decimated
first so a render stays within a few seconds.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import open3d as o3d
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from mpl_toolkits.mplot3d.art3d import Poly3DCollection

from tactile_slam.recon.mesh import MeshError, TriMesh

VIEWS = ((30.0, -60.0), (30.0, 30.0), (30.0, 120.0), (-60.0, 210.0))  # (elevation, azimuth) degrees


def render_views(
    mesh: TriMesh,
    path: str | Path,
    views: tuple[tuple[float, float], ...] = VIEWS,
    max_faces: int = 20000,
    size_px: int = 1000,
) -> Path:
    """Render ``mesh`` (metres) from each ``(elevation, azimuth)`` into one PNG grid.

    Axes are in millimetres. Returns the written path.
    """
    if mesh.n_faces == 0:
        raise MeshError("cannot render a mesh without faces")
    m = mesh.to_open3d()
    if len(m.triangles) > max_faces:
        m = m.simplify_quadric_decimation(max_faces)
    m.compute_triangle_normals()
    v = np.asarray(m.vertices) * 1000.0
    f = np.asarray(m.triangles)
    tris = v[f]
    fn = np.asarray(m.triangle_normals)
    centre = (v.max(0) + v.min(0)) / 2
    half = (v.max(0) - v.min(0)).max() / 2 * 1.05 + 1e-9
    cols = int(np.ceil(np.sqrt(len(views))))
    rows = int(np.ceil(len(views) / cols))
    fig = Figure(figsize=(size_px / 100 * cols / max(rows, cols), size_px / 100 * rows / max(rows, cols)), dpi=100)
    FigureCanvasAgg(fig)
    for k, (elev, azim) in enumerate(views):
        ax = fig.add_subplot(rows, cols, k + 1, projection="3d")
        e, a = np.radians(elev), np.radians(azim)
        eye = np.array([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)])
        light = eye / np.linalg.norm(eye)
        shade = 0.25 + 0.75 * np.clip(fn @ light, 0.0, 1.0)
        colours = np.stack([shade * 0.85, shade * 0.75, shade * 0.6, np.ones_like(shade)], axis=1)
        ax.add_collection3d(Poly3DCollection(tris, facecolors=colours, edgecolors="none"))
        for axis, c in zip("xyz", centre):
            getattr(ax, f"set_{axis}lim")(c - half, c + half)
        ax.set_box_aspect((1, 1, 1))
        ax.view_init(elev=elev, azim=azim)
        ax.set_xlabel("x (mm)")
        ax.set_ylabel("y (mm)")
        ax.set_zlabel("z (mm)")
        ax.set_title(f"elev {elev:.0f}, azim {azim:.0f}", fontsize=8)
        ax.tick_params(labelsize=6)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    return path
