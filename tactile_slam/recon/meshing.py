"""Watertight re-meshing of the fused surface (method.md 8.3).

Oriented fused points -> voxel averaging -> Open3D screened Poisson reconstruction ->
clean-up. ``watertight=True`` keeps the closed Poisson surface and removes only
junk (small disconnected pieces, degenerate faces); it suits fully scanned objects.
``watertight=False`` also trims what the data does not support (low Poisson density,
far from every input point), which suits partial scans but opens the surface.

Poisson runs in millimetres (its defaults assume unit-scale data); input and output
are metres.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence

import numpy as np
import open3d as o3d
import torch
from scipy.spatial import cKDTree

from tactile_slam.config import ConfigError, ReconConfig
from tactile_slam.recon.fusion import FusedKeyframe, ReconError
from tactile_slam.recon.mesh import TriMesh, face_components, is_closed_manifold


def oriented_points(fused: Sequence[FusedKeyframe], min_weight: float
                    ) -> tuple[list[torch.Tensor], list[torch.Tensor]]:
    """Fused points and outward normals for Poisson, in the start frame (metres), one
    part per keyframe (never concatenated: a large scan has tens of millions).

    Keeps points whose own boundary weight is at least ``min_weight`` (away from the
    keyframe's contact edge) and whose normal faces the keyframe's outward side
    (positive dot product with its -z axis).

    Returns:
        the ``(N_k, 3)`` float32 points and the ``(N_k, 3)`` float32 unit normals of
        each keyframe that keeps any (two lists).
    """
    pts, nrm = [], []
    for fk in fused:
        keep = (fk.weights >= min_weight) & (fk.normals @ fk.outward > 0)
        if bool(keep.any()):
            pts.append(fk.points[keep])
            nrm.append(fk.normals[keep])
    if not pts:
        raise ReconError("no fused points away from contact boundaries: nothing to mesh")
    return pts, nrm


_KEY_BITS = 21  # per axis: voxel indices in [-2^20, 2^20)


def voxel_indices(points: torch.Tensor, voxel: float) -> torch.Tensor:
    """Integer indices ``(i, j, k)`` of the cubic voxels (side ``voxel``, grid anchored
    at the origin) holding ``(N, 3)`` points: ``(N, 3)`` int64. Raises
    :class:`ReconError` for NaN or Inf and beyond 2^20 voxels from the origin (the
    range :func:`voxel_keys` packs)."""
    if not bool(torch.isfinite(points).all()):
        raise ReconError("points to bin into voxels contain NaN or Inf")
    idx = torch.floor(points / voxel).long()
    half = 1 << (_KEY_BITS - 1)
    if idx.numel() and int(idx.abs().max()) >= half:
        raise ReconError(f"points lie more than {half} voxels of {voxel:g} from the origin")
    return idx


def pack_keys(idx: torch.Tensor) -> torch.Tensor:
    """One int64 key per row of ``(N, 3)`` voxel indices from :func:`voxel_indices`,
    ordered as the indices lexicographically: ``(N,)``."""
    key = idx + (1 << (_KEY_BITS - 1))
    return (key[:, 0] << (2 * _KEY_BITS)) | (key[:, 1] << _KEY_BITS) | key[:, 2]


def voxel_keys(points: torch.Tensor, voxel: float) -> torch.Tensor:
    """One int64 key per cubic voxel (side ``voxel``, grid anchored at the origin) of
    ``(N, 3)`` points, ordered as the voxel indices ``(i, j, k)`` lexicographically.
    ``(N,)``; raises :class:`ReconError` for NaN or Inf and beyond 2^20 voxels from the origin."""
    return pack_keys(voxel_indices(points, voxel))


def bin_sums(idx: torch.Tensor, values: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Sum ``(N, C)`` values per distinct row of ``(N, 3)`` voxel indices.

    When the indices' bounding box has at most ``max(4 N, 4096)`` cells (points that
    come from one keyframe's contact do), the sums go into that dense box and its
    occupied cells are read in order; otherwise through :func:`torch.unique`. Both
    give the same keys in the same (sorted) order and add each voxel's values in input
    order, so the results are identical.

    Returns:
        ``(M,)`` sorted keys (:func:`pack_keys`) and their ``(M, C)`` sums.
    """
    n = idx.shape[0]
    if n:
        lo = idx.min(dim=0).values
        d = (idx.max(dim=0).values - lo + 1).tolist()
        if d[0] * d[1] * d[2] <= max(4 * n, 4096):
            local = idx - lo
            lin = (local[:, 0] * d[1] + local[:, 1]) * d[2] + local[:, 2]
            cells = d[0] * d[1] * d[2]
            sums = values.new_zeros(cells, values.shape[1]).index_add_(0, lin, values)
            hit = torch.zeros(cells, dtype=torch.bool, device=idx.device)
            hit[lin] = True
            occupied = hit.nonzero()[:, 0]
            ijk = torch.stack([occupied // (d[1] * d[2]), occupied // d[2] % d[1], occupied % d[2]], dim=1)
            return pack_keys(ijk + lo), sums[occupied]
    uniq, inv = torch.unique(pack_keys(idx), return_inverse=True)
    return uniq, values.new_zeros(uniq.shape[0], values.shape[1]).index_add_(0, inv, values)


def voxel_sums(parts: Iterable[tuple[torch.Tensor, torch.Tensor]], voxel: float, chunk: int = 1 << 16
               ) -> torch.Tensor:
    """Sum values per cubic voxel (side ``voxel``, grid anchored at the origin) over
    parts of ``(N, 3)`` points with their ``(N, C)`` values: ``(M, C)`` sums, in the
    order of :func:`voxel_keys`. Each part is summed ``chunk`` points at a time
    (:func:`bin_sums`), then the partial sums per voxel: fused points come keyframe by
    keyframe, so a chunk covers few voxels and no sort or copy runs over all the points.
    No points at all raise :class:`ReconError`."""
    keys, sums = [], []
    for points, values in parts:
        for a in range(0, points.shape[0], chunk):
            k, v = bin_sums(voxel_indices(points[a:a + chunk], voxel), values[a:a + chunk])
            keys.append(k)
            sums.append(v)
    if not sums:
        raise ReconError("no points to bin into voxels")
    if len(sums) == 1:
        return sums[0]
    uniq, inv = torch.unique(torch.cat(keys), return_inverse=True)
    return sums[0].new_zeros(uniq.shape[0], sums[0].shape[1]).index_add_(0, inv, torch.cat(sums))


def voxel_average(
    points: torch.Tensor | Sequence[torch.Tensor], normals: torch.Tensor | Sequence[torch.Tensor], voxel: float,
    max_points: int | None = None, scale: float = 1.0,
) -> tuple[torch.Tensor, torch.Tensor, float]:
    """Average points and normals per cubic voxel of side ``voxel``, coarsened until
    at most ``max_points`` voxels remain.

    A coarser voxel is an integer multiple of ``voxel`` (surface samples thin out as
    ``1 / voxel^2``: each retry multiplies it by about ``1.05 sqrt(M / max_points)``,
    M the voxels at the current size). The first retry only counts the voxels at
    ``voxel`` (one sort of their keys) and bins the points at the coarser size
    directly; later ones re-bin the coarser voxels' centroids with their sums. A
    coarser voxel is a union of finer ones, so either way the result is the average of
    the original points per final voxel.

    Args:
        points: ``(N, 3)``, or a list of parts ``(N_k, 3)`` (e.g. one per keyframe).
        normals: matching ``(N, 3)`` or parts.
        voxel: in the units of ``points * scale``.
        max_points: voxel budget (``None``: none).
        scale: unit factor applied to each part's points before binning.

    Returns:
        ``(M, 3)`` points (in the scaled units), ``(M, 3)`` unit normals, the voxel size used.
    """
    if max_points is not None and max_points < 1:
        raise ReconError(f"recon.poisson_max_points must be >= 1 (or None for no budget), got {max_points}")
    if isinstance(points, torch.Tensor):
        points, normals = [points], [normals]

    def scaled(p: torch.Tensor) -> torch.Tensor:
        return p * scale if scale != 1.0 else p

    def rows():  # (points, [points | normals | 1]) per part, scaled one part at a time
        for p, n in zip(points, normals):
            p = scaled(p)
            yield p, torch.cat([p, n, torch.ones_like(p[:, :1])], dim=1)

    factor = 1
    if max_points is not None:
        keys = [voxel_keys(scaled(p), voxel) for p in points]
        if not keys or sum(k.shape[0] for k in keys) == 0:
            raise ReconError("no points to bin into voxels")
        count = torch.unique(torch.cat(keys)).shape[0]
        del keys
        if count > max_points:
            factor = math.ceil(1.05 * math.sqrt(count / max_points))
    sums = voxel_sums(rows(), voxel * factor)
    while max_points is not None and sums.shape[0] > max_points:
        factor = math.ceil(factor * 1.05 * math.sqrt(sums.shape[0] / max_points))
        sums = voxel_sums([(sums[:, :3] / sums[:, 6:], sums)], voxel * factor)
    return sums[:, :3] / sums[:, 6:], torch.nn.functional.normalize(sums[:, 3:6], dim=1), voxel * factor


def poisson_depth(extent_mm: float, cell_mm: float, min_depth: int, max_depth: int) -> int:
    """Octree depth giving a finest cell of about ``cell_mm`` over ``1.1 * extent_mm``,
    clamped to ``[min_depth, max_depth]``."""
    d = math.ceil(math.log2(max(1.1 * extent_mm / cell_mm, 2.0)))
    return int(min(max(d, min_depth), max_depth))


def poisson_mesh(
    points: torch.Tensor | Sequence[torch.Tensor], normals: torch.Tensor | Sequence[torch.Tensor],
    config: ReconConfig, watertight: bool | None = None,
) -> tuple[TriMesh, dict]:
    """Screened Poisson surface from oriented points.

    Args:
        points: ``(N, 3)`` metres (already voxel-averaged or not), or a list of
            parts (:func:`oriented_points`).
        normals: ``(N, 3)`` outward unit normals, or matching parts.
        config: ``voxel_mm``, ``poisson_cell_mm``, ``poisson_max_points`` (beyond it
            the voxel and the cell grow together), depth bounds, trimming settings.
        watertight: override ``config.watertight``.

    Returns:
        the mesh in metres (same frame as the points) and statistics (depth, counts,
        whether it is closed: edge- and vertex-manifold without boundary edges).
    """
    count = points.shape[0] if isinstance(points, torch.Tensor) else sum(p.shape[0] for p in points)
    if count < 10:
        raise ReconError(f"Poisson meshing needs at least 10 oriented points, got {count}")
    try:
        config.check()
    except ConfigError as exc:
        raise ReconError(str(exc)) from None
    watertight = config.watertight if watertight is None else watertight
    p_mm, n, voxel = voxel_average(points, normals, config.voxel_mm, config.poisson_max_points, scale=1000.0)
    cell = config.poisson_cell_mm * voxel / config.voxel_mm  # the cell follows a coarsened voxel
    extent = float((p_mm.max(dim=0).values - p_mm.min(dim=0).values).max())
    depth = poisson_depth(extent, cell, config.poisson_min_depth, config.poisson_max_depth)
    pcd = o3d.geometry.PointCloud()
    pcd.points = o3d.utility.Vector3dVector(p_mm.cpu().double().numpy())
    pcd.normals = o3d.utility.Vector3dVector(n.cpu().double().numpy())
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        mesh, dens = o3d.geometry.TriangleMesh.create_from_point_cloud_poisson(
            pcd, depth=depth, scale=1.1, linear_fit=False, n_threads=config.poisson_threads
        )
    dens = np.asarray(dens)
    if not watertight:
        drop = dens < np.quantile(dens, config.trim_density_quantile)
        dist, _ = cKDTree(p_mm.cpu().numpy()).query(np.asarray(mesh.vertices), k=1)
        drop |= dist > config.trim_distance_mm
        mesh.remove_vertices_by_mask(drop)
    mesh.merge_close_vertices(1e-3)  # marching-cubes slivers (1 um) -> degenerate faces
    mesh.remove_degenerate_triangles()
    mesh.remove_duplicated_triangles()
    mesh = _largest_component(mesh)
    mesh.remove_unreferenced_vertices()
    if len(mesh.triangles) == 0:
        raise ReconError("Poisson meshing left no triangles")
    mesh.scale(1e-3, center=np.zeros(3))
    mesh.compute_vertex_normals()
    stats = {
        "poisson_depth": depth,
        "voxel_mm": voxel,
        "poisson_points": int(p_mm.shape[0]),
        "vertices": len(mesh.vertices),
        "faces": len(mesh.triangles),
        "closed": is_closed_manifold(np.asarray(mesh.triangles)),
    }
    return TriMesh.from_open3d(mesh), stats


def _largest_component(mesh: o3d.geometry.TriangleMesh) -> o3d.geometry.TriangleMesh:
    """Keep the edge-connected component with the most triangles (the first on ties)."""
    if len(mesh.triangles) == 0:
        return mesh
    labels = face_components(np.asarray(mesh.triangles))
    mesh.remove_triangles_by_mask(labels != int(np.argmax(np.bincount(labels))))
    mesh.remove_unreferenced_vertices()
    return mesh
