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
from collections.abc import Sequence

import numpy as np
import open3d as o3d
import torch
from scipy.spatial import cKDTree

from tactile_slam.config import ReconConfig
from tactile_slam.recon.fusion import FusedKeyframe, ReconError
from tactile_slam.recon.mesh import TriMesh


def oriented_points(fused: Sequence[FusedKeyframe], min_weight: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Fused points and outward normals for Poisson, in the start frame (metres).

    Keeps points whose own boundary weight is at least ``min_weight`` (away from the
    keyframe's contact edge) and whose normal faces the keyframe's outward side
    (positive dot product with its -z axis).

    Returns:
        ``(N, 3)`` float32 points, ``(N, 3)`` float32 unit normals.
    """
    pts, nrm = [], []
    for fk in fused:
        keep = (fk.weights >= min_weight) & (fk.normals @ fk.outward > 0)
        p, n = fk.points[keep], fk.normals[keep]
        pts.append(p)
        nrm.append(n)
    if not pts or sum(p.shape[0] for p in pts) == 0:
        raise ReconError("no fused points away from contact boundaries: nothing to mesh")
    return torch.cat(pts), torch.cat(nrm)


def voxel_sums(points: torch.Tensor, values: torch.Tensor, voxel: float) -> torch.Tensor:
    """Sum ``(N, C)`` values per cubic voxel (side ``voxel``, grid anchored at the
    origin) of their ``(N, 3)`` points: ``(M, C)`` sums, ``M <= N``."""
    key = torch.floor(points / voxel).long()
    key = key - key.min(dim=0).values
    dims = key.max(dim=0).values + 1
    flat = (key[:, 0] * dims[1] + key[:, 1]) * dims[2] + key[:, 2]
    uniq, inv = torch.unique(flat, return_inverse=True)
    return torch.zeros(uniq.shape[0], values.shape[1], dtype=values.dtype, device=values.device).index_add_(
        0, inv, values)


def voxel_average(
    points: torch.Tensor, normals: torch.Tensor, voxel: float, max_points: int | None = None
) -> tuple[torch.Tensor, torch.Tensor, float]:
    """Average points and normals per cubic voxel of side ``voxel`` (same units),
    coarsened until at most ``max_points`` voxels remain.

    A coarser voxel is an integer multiple of ``voxel`` (surface samples thin out as
    ``1 / voxel^2``: each retry multiplies it by about ``1.05 sqrt(M / max_points)``),
    so its voxels are unions of the finer ones and re-binning the finer voxels'
    centroids with their sums gives exactly the average of the original points.

    Returns:
        ``(M, 3)`` points, ``(M, 3)`` unit normals, the voxel size used.
    """
    if max_points is not None and max_points < 1:
        raise ReconError(f"recon.poisson_max_points must be >= 1 (or None for no budget), got {max_points}")
    ones = torch.ones_like(points[:, :1])
    sums = voxel_sums(points, torch.cat([points, normals, ones], dim=1), voxel)
    factor = 1
    while max_points is not None and sums.shape[0] > max_points:
        factor = math.ceil(factor * 1.05 * math.sqrt(sums.shape[0] / max_points))
        sums = voxel_sums(sums[:, :3] / sums[:, 6:], sums, voxel * factor)
    return sums[:, :3] / sums[:, 6:], torch.nn.functional.normalize(sums[:, 3:6], dim=1), voxel * factor


def poisson_depth(extent_mm: float, cell_mm: float, min_depth: int, max_depth: int) -> int:
    """Octree depth giving a finest cell of about ``cell_mm`` over ``1.1 * extent_mm``,
    clamped to ``[min_depth, max_depth]``."""
    d = math.ceil(math.log2(max(1.1 * extent_mm / cell_mm, 2.0)))
    return int(min(max(d, min_depth), max_depth))


def poisson_mesh(
    points: torch.Tensor, normals: torch.Tensor, config: ReconConfig, watertight: bool | None = None
) -> tuple[TriMesh, dict]:
    """Screened Poisson surface from oriented points.

    Args:
        points: ``(N, 3)`` metres (already voxel-averaged or not).
        normals: ``(N, 3)`` outward unit normals.
        config: ``voxel_mm``, ``poisson_cell_mm``, ``poisson_max_points`` (beyond it
            the voxel and the cell grow together), depth bounds, trimming settings.
        watertight: override ``config.watertight``.

    Returns:
        the mesh in metres (same frame as the points) and statistics (depth, counts,
        whether it is closed: edge- and vertex-manifold without boundary edges).
    """
    if points.shape[0] < 10:
        raise ReconError(f"Poisson meshing needs at least 10 oriented points, got {points.shape[0]}")
    watertight = config.watertight if watertight is None else watertight
    p_mm, n, voxel = voxel_average(points * 1000.0, normals, config.voxel_mm,
                                   config.poisson_max_points)
    cell = config.poisson_cell_mm * voxel / config.voxel_mm  # the cell follows a coarsened voxel
    extent = float((p_mm.max(dim=0).values - p_mm.min(dim=0).values).max())
    depth = poisson_depth(extent, cell, config.poisson_min_depth, config.poisson_max_depth)
    pcd = o3d.geometry.PointCloud()
    pcd.points = o3d.utility.Vector3dVector(p_mm.cpu().double().numpy())
    pcd.normals = o3d.utility.Vector3dVector(n.cpu().double().numpy())
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        mesh, dens = o3d.geometry.TriangleMesh.create_from_point_cloud_poisson(
            pcd, depth=depth, scale=1.1, linear_fit=False
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
        "closed": bool(mesh.is_edge_manifold(allow_boundary_edges=False) and mesh.is_vertex_manifold()),
    }
    return TriMesh.from_open3d(mesh), stats


def _largest_component(mesh: o3d.geometry.TriangleMesh) -> o3d.geometry.TriangleMesh:
    if len(mesh.triangles) == 0:
        return mesh
    labels, counts, _ = mesh.cluster_connected_triangles()
    labels = np.asarray(labels)
    mesh.remove_triangles_by_mask(labels != int(np.argmax(np.asarray(counts))))
    mesh.remove_unreferenced_vertices()
    return mesh
