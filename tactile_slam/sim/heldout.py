"""Held-out shapes: meshes outside the catalogue, for checking that the system generalises.

Every catalogue object (:mod:`tactile_slam.sim.objects`) is a convex base shape with a
displacement texture, and every threshold of the system was chosen while looking at
them. These three shapes differ in kind, and reach the simulator the way a user's CAD
file does (a mesh file, ``tactile-slam simulate --object FILE``):

* ``torus``: a ring (major radius 9 mm, tube 4 mm) with a rough-cast relief: the only
  shape with saddles (negative Gaussian curvature) and a hole;
* ``screw``: a 22 mm capsule of radius 5 mm with a helical thread (pitch 1.6 mm, depth
  0.3 mm) and smooth, untextured end caps: a helical motion maps the thread onto itself;
* ``rock``: a 20 mm sphere whose radius carries random relief at every scale from 0.4 to
  12 mm, so it has no single texture period and slopes steeper than the presses.

The relief is a sum of plane waves with random directions, wavelengths and phases
(amplitude proportional to the wavelength), evaluated on the base point, so it has no
seams. Lengths are mm while building; the meshes are returned in metres.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import open3d as o3d

SHAPES = ("torus", "screw", "rock")


def plane_waves(p: np.ndarray, rng: np.random.Generator, n: int, wavelength_mm: tuple[float, float],
                slope: float) -> np.ndarray:
    """Relief at points ``p`` ``(V, 3)`` mm: ``sum_k a_k sin(2 pi d_k . p / l_k + phi_k)``
    over ``n`` waves with random unit directions, log-uniform wavelengths ``l_k`` in
    ``wavelength_mm`` and amplitude ``a_k = slope * l_k``. Returns ``(V,)`` mm."""
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    lam = np.exp(rng.uniform(np.log(wavelength_mm[0]), np.log(wavelength_mm[1]), n))
    phase = rng.uniform(0.0, 2.0 * np.pi, n)
    return np.sin(2.0 * np.pi * (p @ d.T) / lam + phase) @ (slope * lam)


def grid_mesh(points: np.ndarray, wrap_v: bool) -> o3d.geometry.TriangleMesh:
    """Triangulate a ``(U, V, 3)`` grid of points, periodic in u and, if ``wrap_v``, in v;
    coincident points (the poles of a closed surface of revolution) are welded. The
    winding is made outward (positive volume)."""
    nu, nv = points.shape[:2]
    idx = np.arange(nu * nv).reshape(nu, nv)
    i = np.arange(nu)[:, None]
    j = np.arange(nv if wrap_v else nv - 1)[None]
    a, b = idx[i, j % nv], idx[(i + 1) % nu, j % nv]
    c, d = idx[(i + 1) % nu, (j + 1) % nv], idx[i, (j + 1) % nv]
    tri = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3), np.stack([a, c, d], -1).reshape(-1, 3)])
    mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(points.reshape(-1, 3)),
                                     o3d.utility.Vector3iVector(tri))
    mesh.remove_duplicated_vertices()
    mesh.remove_degenerate_triangles()
    mesh.remove_unreferenced_vertices()
    v, t = np.asarray(mesh.vertices), np.asarray(mesh.triangles)
    if np.einsum("ij,ij->i", v[t[:, 0]], np.cross(v[t[:, 1]], v[t[:, 2]])).sum() < 0:
        mesh.triangles = o3d.utility.Vector3iVector(t[:, ::-1].copy())
    return mesh


def _steps(length_mm: float, resolution_mm: float) -> int:
    return max(int(round(length_mm / resolution_mm)), 8)


def torus(resolution_mm: float = 0.08, seed: int = 0) -> o3d.geometry.TriangleMesh:
    """The ring, in metres (see the module docstring)."""
    rng = np.random.default_rng(seed)
    big, small = 9.0, 4.0
    u = np.linspace(0.0, 2.0 * np.pi, _steps(2.0 * np.pi * (big + small), resolution_mm), endpoint=False)
    v = np.linspace(0.0, 2.0 * np.pi, _steps(2.0 * np.pi * small, resolution_mm), endpoint=False)
    U, V = np.meshgrid(u, v, indexing="ij")
    normal = np.stack([np.cos(V) * np.cos(U), np.cos(V) * np.sin(U), np.sin(V)], -1)
    base = np.stack([big * np.cos(U), big * np.sin(U), np.zeros_like(U)], -1) + small * normal
    relief = plane_waves(base.reshape(-1, 3), rng, 120, (0.4, 3.0), 0.012).reshape(U.shape)
    return _finish(grid_mesh(base + relief[..., None] * normal, wrap_v=True))


def screw(resolution_mm: float = 0.08, seed: int = 0) -> o3d.geometry.TriangleMesh:
    """The threaded capsule, in metres (see the module docstring); ``seed`` turns the
    thread's start."""
    rng = np.random.default_rng(seed)
    radius, length, pitch, depth = 5.0, 22.0, 1.6, 0.3
    half = length / 2.0 - radius  # the cylinder's half length; the caps are hemispheres
    n_cap = _steps(np.pi / 2.0 * radius, resolution_mm)
    phi = np.concatenate([np.linspace(-np.pi / 2.0, 0.0, n_cap, endpoint=False),
                          np.zeros(_steps(2.0 * half, resolution_mm)),
                          np.linspace(0.0, np.pi / 2.0, n_cap + 1)])
    z = np.concatenate([-half + radius * np.sin(phi[:n_cap]),
                        np.linspace(-half, half, len(phi) - 2 * n_cap - 1, endpoint=False),
                        half + radius * np.sin(phi[-n_cap - 1:])])
    r = radius * np.cos(phi)
    r[[0, -1]] = 0.0  # exact poles, welded by grid_mesh
    theta = np.linspace(0.0, 2.0 * np.pi, _steps(2.0 * np.pi * radius, resolution_mm), endpoint=False)
    TH, Z = np.meshgrid(theta, z, indexing="ij")
    R = np.broadcast_to(r, TH.shape)
    u = (Z - pitch * TH / (2.0 * np.pi)) / pitch + rng.uniform()
    ridge = 1.0 - 4.0 * np.abs(u - np.floor(u) - 0.5)  # triangular wave in [-1, 1]
    thread = 0.5 * depth * (np.tanh(2.5 * ridge) / np.tanh(2.5) + 1.0)  # flattened crests, [0, depth]
    fade = np.clip(half + 0.5 - np.abs(Z), 0.0, 1.0)  # the thread runs out over 1 mm at the caps
    R = R + (thread - depth) * fade
    return _finish(grid_mesh(np.stack([R * np.cos(TH), R * np.sin(TH), Z], -1), wrap_v=False))


def rock(resolution_mm: float = 0.08, seed: int = 0) -> o3d.geometry.TriangleMesh:
    """The irregular stone, in metres (see the module docstring)."""
    rng = np.random.default_rng(seed)
    radius = 10.0
    level = int(np.clip(np.ceil(np.log2(1.05 * radius / resolution_mm)), 1, 8))
    sphere = o3d.geometry.TriangleMesh.create_icosahedron(1.0).subdivide_midpoint(level)
    d = np.asarray(sphere.vertices)
    d = d / np.linalg.norm(d, axis=1, keepdims=True)
    r = radius + plane_waves(d * radius, rng, 200, (0.4, 12.0), 0.02)
    sphere.vertices = o3d.utility.Vector3dVector(d * r[:, None])
    return _finish(sphere)


def _finish(mesh: o3d.geometry.TriangleMesh) -> o3d.geometry.TriangleMesh:
    mesh.scale(1e-3, center=np.zeros(3))
    mesh.compute_vertex_normals()
    return mesh


def make_heldout(name: str, resolution_mm: float = 0.08, seed: int = 0) -> o3d.geometry.TriangleMesh:
    """One of :data:`SHAPES` as a closed mesh in metres, centred on the origin."""
    builders = {"torus": torus, "screw": screw, "rock": rock}
    if name not in builders:
        raise ValueError(f"unknown held-out shape {name!r}; choose one of {list(SHAPES)}")
    if not (np.isfinite(resolution_mm) and resolution_mm > 0):
        raise ValueError(f"resolution_mm must be > 0, got {resolution_mm}")
    return builders[name](resolution_mm, seed)


def write_heldout(out_dir: str | Path, names: tuple[str, ...] = SHAPES, resolution_mm: float = 0.08,
                  seed: int = 0) -> list[Path]:
    """Write the shapes as ``OUT/<name>.ply`` (metres: simulate them with the default
    ``--mesh-scale 1``) and return the paths."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = []
    for name in names:
        path = out / f"{name}.ply"
        if not o3d.io.write_triangle_mesh(str(path), make_heldout(name, resolution_mm, seed)):
            raise OSError(f"could not write {path}")
        paths.append(path)
    return paths
