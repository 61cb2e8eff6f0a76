"""Surface queries on object meshes: area-uniform sampling, farthest-point subsets, and
closest points with normals smoothed at the scale of a tactile contact."""

from __future__ import annotations

import numpy as np
import open3d as o3d


def sample_triangles(vertices: np.ndarray, triangles: np.ndarray, n: int,
                     rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Area-uniform random points on triangles ``vertices[triangles]``.

    Args:
        vertices: ``(V, 3)``; triangles: ``(F, 3)`` int; n: number of points.
        rng: random generator (the result is deterministic given its state).

    Returns:
        ``(points (n, 3), normals (n, 3))``: positions and the unit normals of the
        triangles they lie on (the winding decides the side).
    """
    if len(triangles) == 0:
        raise ValueError("cannot sample a mesh without triangles")
    a, b, c = vertices[triangles[:, 0]], vertices[triangles[:, 1]], vertices[triangles[:, 2]]
    cross = np.cross(b - a, c - a)
    area = np.linalg.norm(cross, axis=1)
    if not area.sum() > 0:
        raise ValueError("mesh has zero surface area")
    idx = rng.choice(len(triangles), size=n, p=area / area.sum())
    s, r2 = np.sqrt(rng.random(n)), rng.random(n)
    pts = (1 - s)[:, None] * a[idx] + (s * (1 - r2))[:, None] * b[idx] + (s * r2)[:, None] * c[idx]
    normals = cross[idx] / np.maximum(area[idx], 1e-300)[:, None]
    return pts, normals


def sample_surface(mesh: o3d.geometry.TriangleMesh, n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Area-uniform random points and their triangle normals on ``mesh`` (its units);
    see :func:`sample_triangles`."""
    return sample_triangles(np.asarray(mesh.vertices), np.asarray(mesh.triangles), n, rng)


def farthest_points(points: np.ndarray, k: int, start: int = 0) -> np.ndarray:
    """Indices of ``k`` points chosen by farthest-point sampling (a Poisson-disk-like,
    deterministic cover). ``points`` ``(N, 3)`` -> ``(k,)`` int64."""
    n = len(points)
    if not 0 < k <= n:
        raise ValueError(f"cannot choose {k} of {n} points")
    chosen = np.empty(k, dtype=np.int64)
    chosen[0] = start
    dist = np.linalg.norm(points - points[start], axis=1)
    for i in range(1, k):
        chosen[i] = int(np.argmax(dist))
        dist = np.minimum(dist, np.linalg.norm(points - points[chosen[i]], axis=1))
    return chosen


def _as_points(points: np.ndarray) -> np.ndarray:
    """``points`` as a float64 ``(N, 3)`` array; a clear error for another shape or a
    non-finite coordinate."""
    points = np.asarray(points, dtype=np.float64)
    if points.ndim == 1 and points.shape == (3,):
        points = points[None]
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"expected points of shape (N, 3), got {points.shape}")
    if not np.isfinite(points).all():
        raise ValueError("points contain NaN or Inf")
    return points


class SurfaceGuide:
    """Closest points on a mesh and outward normals smoothed over ``smoothing_m``.

    The smoothed normals come from a vertex-clustered copy of the mesh (cells of
    ``smoothing_m``), interpolated barycentrically, so texture below that scale does
    not tilt the sensor. Coarser fields (``scale`` > 1: cells of ``scale * smoothing_m``)
    are built on first use, for surfaces whose relief turns the finest field too fast.

    Args:
        mesh: object mesh in metres with outward winding.
        smoothing_m: scale of the normal smoothing (about the contact radius).
    """

    def __init__(self, mesh: o3d.geometry.TriangleMesh, smoothing_m: float = 8e-4):
        self.mesh = mesh
        self.smoothing_m = smoothing_m
        self.scene = o3d.t.geometry.RaycastingScene()
        self.scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(mesh))
        self._fields: dict[float, tuple | None] = {}
        self._field(1.0)

    def _built(self, scale: float) -> tuple | None:
        """The normal field at ``scale`` (raycasting scene, triangles, vertex normals),
        built on first use; ``None`` where its cells leave the object no triangles."""
        if not (np.isfinite(scale) and scale > 0):
            raise ValueError(f"a normal-field scale must be a finite number > 0, got {scale!r}")
        if scale not in self._fields:
            coarse = self.mesh.simplify_vertex_clustering(self.smoothing_m * scale)
            coarse.remove_degenerate_triangles()
            field = None
            if len(coarse.triangles):
                coarse.compute_vertex_normals()
                scene = o3d.t.geometry.RaycastingScene()
                scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(coarse))
                field = scene, np.asarray(coarse.triangles), np.asarray(coarse.vertex_normals)
            self._fields[scale] = field
        return self._fields[scale]

    def _field(self, scale: float) -> tuple:
        """The normal field at ``scale``; a clear error where it does not exist."""
        field = self._built(scale)
        if field is None:
            raise ValueError(f"the normal field at scale {scale} ({self.smoothing_m * scale * 1e3:.3g} mm cells) "
                             "leaves no triangles: the scale is too coarse for this object")
        return field

    def resolves(self, scale: float) -> bool:
        """Whether a normal field at ``scale`` exists: its cells are small enough to leave
        the object some triangles (a field coarser than the object has none)."""
        return self._built(scale) is not None

    def project(self, points: np.ndarray, scale: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
        """Closest surface points ``(N, 3)`` and smoothed outward normals ``(N, 3)`` (the
        field at ``scale`` times the smoothing)."""
        q = o3d.core.Tensor(_as_points(points).astype(np.float32))
        closest = self.scene.compute_closest_points(q)["points"].numpy().astype(np.float64)
        coarse_scene, coarse_tri, coarse_normals = self._field(scale)
        res = coarse_scene.compute_closest_points(o3d.core.Tensor(closest.astype(np.float32)))
        ids = res["primitive_ids"].numpy().astype(np.int64)
        uv = res["primitive_uvs"].numpy().astype(np.float64)
        vn = coarse_normals[coarse_tri[ids]]  # (N, 3 vertices, 3)
        w = np.stack([1 - uv[:, 0] - uv[:, 1], uv[:, 0], uv[:, 1]], -1)
        n = np.einsum("nk,nkd->nd", w, vn)
        norm = np.linalg.norm(n, axis=1, keepdims=True)
        fine = res["primitive_normals"].numpy().astype(np.float64)  # coarse face normal as fallback
        n = np.where(norm > 1e-3, n / np.maximum(norm, 1e-12), fine)
        return closest, n / np.linalg.norm(n, axis=1, keepdims=True)

    def walk(self, targets: np.ndarray, scale: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
        """Follow a path of ``targets`` ``(T, 3)`` along the surface instead of projecting
        each one: the first is projected, then every target's step is laid into the tangent
        plane at the current point (its length kept) and the moved point is projected. A
        point never leaves its neighbourhood, so the path cannot jump across a concavity
        to another sheet the way closest points do near the medial axis.

        Returns:
            ``(points (T, 3), normals (T, 3))`` as :meth:`project` (normals at ``scale``).
        """
        targets = _as_points(targets)
        points, normals = np.empty_like(targets), np.empty_like(targets)
        if len(targets) == 0:
            return points, normals
        p, n = self.project(targets[:1], scale)
        points[0], normals[0] = p[0], n[0]
        for i in range(1, len(targets)):
            step = targets[i] - targets[i - 1]
            along = step - np.dot(step, normals[i - 1]) * normals[i - 1]
            size = np.linalg.norm(along)
            if size > 1e-12:
                step = along * (np.linalg.norm(step) / size)
            p, n = self.project(points[i - 1:i] + step, scale)
            points[i], normals[i] = p[0], n[0]
        return points, normals
