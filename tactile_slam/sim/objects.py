"""Procedural test objects: watertight triangle meshes in metres with tactile texture.

Every object is a convex base shape given by an implicit function ``f(p) < 0`` inside
(ellipsoid, rounded box, rounded cylinder), meshed by mapping a subdivided icosahedron
onto it (scale the unit sphere by the half extents, then slide each vertex along its
ray from the origin onto ``f = 0``). The surface texture is a displacement along the
base normal, evaluated as a solid texture on the base point, so there are no seams and
the icosphere's topology (closed, manifold, watertight) is kept.

Sizes are in mm while building; :func:`make_object` returns metres. The texture scale
(0.05-0.5 mm) is what a GelSight Mini at 0.0634 mm/px resolves; the default mesh
resolution (0.08 mm mean edge, at most ~1.3 M triangles) keeps it after the
elastomer's ~0.1 mm smoothing.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Callable
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np
import open3d as o3d
from scipy.spatial import cKDTree

from tactile_slam.sim.surface import sample_triangles


class ObjectError(ValueError):
    """An object name, size or mesh file is invalid, or a setting that does not apply
    to that kind of object was given."""


class MeshSizeWarning(UserWarning):
    """A user mesh, after its scale, is outside :data:`SIZE_RANGE_MM`, the sizes of a
    tactile object: its file is probably in other units than the scale assumes."""


SIZE_RANGE_MM = (2.0, 200.0)
"""Overall sizes (longest extent, mm) of an object a tactile sensor scans: the range the
catalogue accepts and the one a user mesh is checked against."""


# ---------------------------------------------------------------- base shapes (mm)


def _ellipsoid(e: np.ndarray) -> Callable[[np.ndarray], np.ndarray]:
    return lambda p: np.linalg.norm(p / e, axis=-1) - 1.0


def _rounded_box(half: np.ndarray, radius: float) -> Callable[[np.ndarray], np.ndarray]:
    def f(p: np.ndarray) -> np.ndarray:
        q = np.abs(p) - (half - radius)
        outside = np.linalg.norm(np.maximum(q, 0.0), axis=-1)
        return outside + np.minimum(q.max(axis=-1), 0.0) - radius
    return f


def _rounded_cylinder(radius: float, half_length: float, rounding: float) -> Callable[[np.ndarray], np.ndarray]:
    def f(p: np.ndarray) -> np.ndarray:
        d = np.stack([np.hypot(p[:, 0], p[:, 1]) - (radius - rounding), np.abs(p[:, 2]) - (half_length - rounding)], -1)
        return np.linalg.norm(np.maximum(d, 0.0), axis=-1) + np.minimum(d.max(axis=-1), 0.0) - rounding
    return f


@lru_cache(maxsize=4)
def _unit_icosphere(level: int) -> tuple[np.ndarray, np.ndarray]:
    mesh = o3d.geometry.TriangleMesh.create_icosahedron(1.0).subdivide_midpoint(level)
    v = np.asarray(mesh.vertices)
    v = v / np.linalg.norm(v, axis=1, keepdims=True)
    return v, np.asarray(mesh.triangles).copy()


def _project_to_shape(dirs: np.ndarray, f: Callable[[np.ndarray], np.ndarray], r_max: float) -> np.ndarray:
    """Slide points along their rays from the origin onto ``f = 0`` (star-shaped f).
    ``dirs`` (V, 3) unit vectors -> (V, 3) surface points."""
    lo = np.zeros(len(dirs))
    hi = np.full(len(dirs), r_max)
    for _ in range(32):
        mid = 0.5 * (lo + hi)
        inside = f(dirs * mid[:, None]) < 0
        lo = np.where(inside, mid, lo)
        hi = np.where(inside, hi, mid)
    return dirs * (0.5 * (lo + hi))[:, None]


def _implicit_normals(p: np.ndarray, f: Callable[[np.ndarray], np.ndarray], eps: float = 1e-4) -> np.ndarray:
    g = np.stack([f(p + eps * e) - f(p - eps * e) for e in np.eye(3)], -1)
    return g / np.linalg.norm(g, axis=1, keepdims=True)


@dataclass(frozen=True)
class BaseShape:
    """Implicit convex shape (mm) and the ellipsoid used to distribute vertices."""

    f: Callable[[np.ndarray], np.ndarray]
    half_extents: np.ndarray

    def mesh(self, resolution_mm: float, max_level: int = 8) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Points ``(V, 3)`` mm, outward normals ``(V, 3)`` and triangles ``(F, 3)``."""
        a, b, c = self.half_extents
        p = 1.6075  # Knud Thomsen's ellipsoid-area approximation
        area = 4 * math.pi * (((a * b) ** p + (a * c) ** p + (b * c) ** p) / 3) ** (1 / p)
        edge_at_0 = 1.05 * math.sqrt(area / (4 * math.pi))
        level = int(np.clip(math.ceil(math.log2(max(edge_at_0 / resolution_mm, 1.0))), 1, max_level))
        u, tri = _unit_icosphere(level)
        q = u * self.half_extents
        dirs = q / np.linalg.norm(q, axis=1, keepdims=True)
        pts = _project_to_shape(dirs, self.f, 2.0 * float(np.linalg.norm(self.half_extents)))
        return pts, _implicit_normals(pts, self.f), tri


# ---------------------------------------------------------------- textures (mm)


def _bumps(pts: np.ndarray, centres: np.ndarray, sigma: np.ndarray, height: np.ndarray) -> np.ndarray:
    """Sum of Gaussian bumps ``height * exp(-d^2 / 2 sigma^2)`` cut at 3 sigma. ``(V,)``."""
    tree = cKDTree(pts)
    hits = tree.query_ball_point(centres, r=3.0 * sigma)
    lengths = np.fromiter((len(h) for h in hits), dtype=np.int64, count=len(hits))
    out = np.zeros(len(pts))
    if lengths.sum() == 0:
        return out
    vid = np.concatenate([np.asarray(h, dtype=np.int64) for h in hits])
    cid = np.repeat(np.arange(len(centres)), lengths)
    d2 = np.sum((pts[vid] - centres[cid]) ** 2, axis=1)
    np.add.at(out, vid, height[cid] * np.exp(-0.5 * d2 / sigma[cid] ** 2))
    return out


def _random_bumps(pts, tri, rng, density, sigma_range, height_range) -> np.ndarray:
    a, b, c = pts[tri[:, 0]], pts[tri[:, 1]], pts[tri[:, 2]]
    area = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1).sum()
    n = max(int(density * area), 1)
    centres, _ = sample_triangles(pts, tri, n, rng)
    return _bumps(pts, centres, rng.uniform(*sigma_range, n), rng.uniform(*height_range, n))


def _smoothstep(x: np.ndarray, lo: float, hi: float) -> np.ndarray:
    t = np.clip((x - lo) / (hi - lo), 0.0, 1.0)
    return t * t * (3 - 2 * t)


def _tri_wave(u: np.ndarray) -> np.ndarray:
    """0 at half-integers, 1 at integers (period 1)."""
    return 2.0 * np.abs(u - np.floor(u) - 0.5)


# ---------------------------------------------------------------- catalogue


@dataclass(frozen=True)
class ObjectSpec:
    """A procedural object: default size (mm), base shape and texture builders."""

    default_size_mm: float
    description: str
    shape: Callable[[float], BaseShape]
    texture: Callable[[np.ndarray, np.ndarray, np.ndarray, float, np.random.Generator], np.ndarray]


def _seed_shape(s):
    return BaseShape(_ellipsoid(np.array([0.5, 0.34, 0.28]) * s), np.array([0.5, 0.34, 0.28]) * s)


def _seed_texture(p, n, tri, s, rng):
    return _random_bumps(p, tri, rng, density=3.0, sigma_range=(0.08, 0.18), height_range=(0.05, 0.14))


def _shell_shape(s):
    e = np.array([0.5, 0.42, 0.16]) * s
    return BaseShape(_ellipsoid(e), e)


def _shell_texture(p, n, tri, s, rng):
    hinge = np.array([0.0, -0.42 * s, 0.0])
    rel = p - hinge
    rho = np.hypot(rel[:, 0], rel[:, 1])
    phi = np.arctan2(rel[:, 0], rel[:, 1])  # 0 along +y, away from the hinge
    n_ribs = 22
    rib_width = 0.6 + 0.4 * _smoothstep(rho, 0.0, 0.6 * s)
    ribs = 0.28 * np.cos(0.5 * n_ribs * phi) ** 2 * rib_width * _smoothstep(rho, 0.5, 3.0)
    growth = 0.035 * np.sin(2 * np.pi * rho / 0.45 + rng.uniform(0, 2 * np.pi))
    grain = _random_bumps(p, tri, rng, density=1.0, sigma_range=(0.1, 0.2), height_range=(-0.03, 0.03))
    return ribs + growth + grain


def _dice_shape(s):
    half = np.full(3, 0.5 * s)
    return BaseShape(_rounded_box(half, 0.12 * s), half)


_PIPS = {1: [(0, 0)], 2: [(-1, -1), (1, 1)], 3: [(-1, -1), (0, 0), (1, 1)], 4: [(-1, -1), (-1, 1), (1, -1), (1, 1)],
         5: [(-1, -1), (-1, 1), (0, 0), (1, -1), (1, 1)], 6: [(-1, -1), (-1, 0), (-1, 1), (1, -1), (1, 0), (1, 1)]}


def _dice_texture(p, n, tri, s, rng):
    faces = [(2, +1, 1), (2, -1, 6), (0, +1, 2), (0, -1, 5), (1, +1, 3), (1, -1, 4)]
    pip_r, pip_depth, spacing = 0.09 * s, 0.035 * s, 0.27 * s
    d = np.zeros(len(p))
    for axis, sign, count in faces:
        others = [k for k in range(3) if k != axis]
        on_face = sign * p[:, axis] > 0.3 * s
        for u, v in _PIPS[count]:
            rho = np.hypot(p[:, others[0]] - u * spacing, p[:, others[1]] - v * spacing)
            d -= on_face * pip_depth * np.clip(1 - (rho / pip_r) ** 2, 0, None) ** 1.5
    layers = 0.012 * np.sin(2 * np.pi * p[:, 2] / 0.25)
    grain = _random_bumps(p, tri, rng, density=1.5, sigma_range=(0.08, 0.15), height_range=(-0.02, 0.02))
    return d + layers + grain


def _lime_shape(s):
    e = np.array([0.5, 0.48, 0.46]) * s
    return BaseShape(_ellipsoid(e), e)


def _lime_texture(p, n, tri, s, rng):
    return _random_bumps(p, tri, rng, density=3.0, sigma_range=(0.1, 0.22), height_range=(-0.09, -0.03))


def _handle_shape(s):
    r, half_len = 0.5 * s, 1.0 * s
    return BaseShape(_rounded_cylinder(r, half_len, 0.15 * s), np.array([r, r, half_len]))


def _handle_texture(p, n, tri, s, rng):
    theta = np.arctan2(p[:, 1], p[:, 0])
    d = np.zeros(len(p))
    for _ in range(6):  # faint grain: fibres running along the axis, slowly wavy
        k = max(round(2 * np.pi * 0.5 * s / rng.uniform(0.4, 1.5)), 1)
        wobble = 0.3 * np.sin(2 * np.pi * p[:, 2] / rng.uniform(5, 15) + rng.uniform(0, 2 * np.pi))
        d += rng.uniform(0.004, 0.01) * np.sin(k * (theta + wobble / (0.5 * s)) + rng.uniform(0, 2 * np.pi))
    return d


def _ball_shape(s):
    e = np.full(3, 0.5 * s)
    return BaseShape(_ellipsoid(e), e)


def _ball_texture(p, n, tri, s, rng):
    return np.zeros(len(p))


def _knurl_shape(s):
    r, half_len = 0.5 * s, 0.95 * s
    return BaseShape(_rounded_cylinder(r, half_len, 0.1 * s), np.array([r, r, half_len]))


def _knurl_texture(p, n, tri, s, rng):
    r, half_len, pitch, depth = 0.5 * s, 0.95 * s, 1.0, 0.22
    theta = np.arctan2(p[:, 1], p[:, 0])
    n_cells = max(round(2 * np.pi * r / pitch), 1)
    pitch = 2 * np.pi * r / n_cells  # periodic around the circumference
    arc = theta * r
    a, b = (arc + p[:, 2]) / pitch, (arc - p[:, 2]) / pitch
    pyramids = depth * (1.0 - np.maximum(_tri_wave(a - 0.5), _tri_wave(b - 0.5)))
    band = 1.0 - _smoothstep(np.abs(p[:, 2]), half_len - 0.25 * s, half_len - 0.15 * s)
    return (pyramids - depth) * band


def _plane_shape(s):
    half = np.array([0.5 * s, 0.5 * s, 2.5])
    return BaseShape(_rounded_box(half, 1.5), half)


def _plane_texture(p, n, tri, s, rng):
    pitch, amp = 0.8, 0.14
    x, y = p[:, 0] + rng.uniform(0, pitch), p[:, 1] + rng.uniform(0, pitch)
    j, i = np.round(y / pitch), np.round(x / pitch)
    dy, dx = y - j * pitch, x - i * pitch
    prof_y = np.sqrt(np.clip(1 - (dy / (0.5 * pitch)) ** 2, 0, None))
    prof_x = np.sqrt(np.clip(1 - (dx / (0.5 * pitch)) ** 2, 0, None))
    warp = (0.5 + 0.5 * (-1) ** j * np.sin(np.pi * x / pitch)) * prof_y
    weft = (0.5 - 0.5 * (-1) ** i * np.sin(np.pi * y / pitch)) * prof_x
    faces = _smoothstep(np.abs(n[:, 2]), 0.6, 0.9)
    return amp * (np.maximum(warp, weft) - 0.5) * faces


OBJECTS: dict[str, ObjectSpec] = {
    "seed": ObjectSpec(9.0, "ellipsoid 9 mm long, dense bumps (high texture)", _seed_shape, _seed_texture),
    "shell": ObjectSpec(24.0, "flattened ellipsoid 24 mm, radial ribs and growth lines", _shell_shape, _shell_texture),
    "dice": ObjectSpec(12.0, "rounded cube 12 mm with pips and print layers", _dice_shape, _dice_texture),
    "lime": ObjectSpec(22.0, "slightly oblate sphere 22 mm with oil-gland dimples", _lime_shape, _lime_texture),
    "handle": ObjectSpec(20.0, "rounded cylinder 20 mm diameter, faint wood grain (low texture)",
                         _handle_shape, _handle_texture),
    "ball": ObjectSpec(20.0, "smooth sphere 20 mm (textureless: the known failure case)", _ball_shape, _ball_texture),
    "knurled": ObjectSpec(16.0, "cylinder 16 mm diameter with diamond knurl (repetitive: false-loop risk)",
                          _knurl_shape, _knurl_texture),
    "plane": ObjectSpec(30.0, "30 mm square slab with a plain fabric weave on its faces", _plane_shape, _plane_texture),
}


@lru_cache(maxsize=8)
def _build(name: str, size_mm: float, seed: int, resolution_mm: float) -> o3d.geometry.TriangleMesh:
    spec = OBJECTS[name]
    shape = spec.shape(size_mm)
    pts, normals, tri = shape.mesh(resolution_mm)
    rng = np.random.default_rng(seed)
    disp = spec.texture(pts, normals, tri, size_mm, rng)
    verts = (pts + disp[:, None] * normals) * 1e-3
    mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(verts), o3d.utility.Vector3iVector(tri))
    mesh.compute_vertex_normals()
    return mesh


def make_object(name: str, size_mm: float | None = None, seed: int = 0,
                resolution_mm: float = 0.08) -> o3d.geometry.TriangleMesh:
    """Build a procedural object (a fresh copy; builds are cached per process).

    Args:
        name: one of :data:`OBJECTS` (``seed``, ``shell``, ``dice``, ``lime``, ``handle``,
            ``ball``, ``knurled``, ``plane``).
        size_mm: overall size (longest dimension or diameter); ``None`` = the default.
        seed: seed for the random parts of the texture.
        resolution_mm: target mean edge length of the mesh.

    Returns:
        A watertight triangle mesh in metres, centred on the origin, with vertex normals.
    """
    if name not in OBJECTS:
        raise ObjectError(f"unknown object {name!r}; choose one of {sorted(OBJECTS)} or give a mesh file")
    size = OBJECTS[name].default_size_mm if size_mm is None else float(size_mm)
    lo, hi = SIZE_RANGE_MM
    if not (math.isfinite(size) and lo <= size <= hi):
        raise ObjectError(f"object size must be between {lo:g} and {hi:g} mm, got {size_mm}")
    if not (math.isfinite(resolution_mm) and resolution_mm > 0):
        raise ObjectError(f"resolution_mm must be > 0, got {resolution_mm}")
    return o3d.geometry.TriangleMesh(_build(name, size, int(seed), float(resolution_mm)))


def extent_mm(mesh: o3d.geometry.TriangleMesh) -> float:
    """Longest side of the mesh's axis-aligned bounding box, mm (its vertices in metres)."""
    return float(np.ptp(np.asarray(mesh.vertices), axis=0).max() * 1e3)


def load_object(path: str | Path, scale: float = 1.0) -> o3d.geometry.TriangleMesh:
    """Load a user mesh (PLY/OBJ/STL) as an object.

    Args:
        path: mesh file; its units times ``scale`` must be metres (e.g. ``scale=1e-3``
            for a CAD file in mm).

    Returns:
        The mesh in metres with vertex normals; it is not re-centred.

    Warns:
        MeshSizeWarning: the scaled mesh's longest extent is outside
            :data:`SIZE_RANGE_MM` (a file in mm read as metres is 1000 times too large).
    """
    path = Path(path)
    if not path.is_file():
        raise ObjectError(f"mesh file not found: {path}")
    if path.suffix.lower() not in (".ply", ".obj", ".stl"):
        raise ObjectError(f"unsupported mesh format {path.suffix!r} (use .ply, .obj or .stl): {path}")
    mesh = o3d.io.read_triangle_mesh(str(path))
    if len(mesh.triangles) == 0:
        raise ObjectError(f"mesh file has no triangles: {path}")
    verts = np.asarray(mesh.vertices)
    if not np.isfinite(verts).all():
        raise ObjectError(f"mesh file has non-finite vertices: {path}")
    if scale != 1.0:
        mesh.vertices = o3d.utility.Vector3dVector(verts * scale)
    size = extent_mm(mesh)
    lo, hi = SIZE_RANGE_MM
    if not lo <= size <= hi:
        warnings.warn(f"{path} is {size:.4g} mm across with mesh scale {scale:g} (its units to metres), outside the "
                      f"{lo:g}-{hi:g} mm of a tactile object: the file may be in other units; give the scale "
                      "(--mesh-scale), e.g. 1e-3 for a file in mm, 1e-2 in cm, 0.0254 in inches", MeshSizeWarning,
                      stacklevel=2)
    mesh.compute_vertex_normals()
    return mesh


def resolve_object(name_or_path: str, size_mm: float | None = None, seed: int = 0,
                   scale: float | None = None) -> o3d.geometry.TriangleMesh:
    """A catalogue name or a mesh path -> mesh in metres.

    ``size_mm`` applies to catalogue objects only (``None``: the default size) and
    ``scale`` to mesh files only (``None``: 1, the file is in metres); giving one for the
    other kind of object is an :class:`ObjectError` rather than silently ignored.
    """
    if name_or_path in OBJECTS:
        if scale is not None:
            raise ObjectError(f"a mesh scale (--mesh-scale) applies to mesh files, not to the catalogue object "
                              f"{name_or_path!r}; give its size with --size-mm")
        return make_object(name_or_path, size_mm, seed)
    if Path(name_or_path).suffix.lower() in (".ply", ".obj", ".stl"):
        if size_mm is not None:
            raise ObjectError(f"a size (--size-mm) applies to catalogue objects, not to the mesh file {name_or_path}; "
                              "convert its units to metres with --mesh-scale")
        return load_object(name_or_path, 1.0 if scale is None else scale)
    raise ObjectError(f"unknown object {name_or_path!r}; choose one of {sorted(OBJECTS)} or give a mesh file")
