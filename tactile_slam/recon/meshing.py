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
        ``(N, 3)`` float64 points, ``(N, 3)`` float64 unit normals.
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


def voxel_average(points: torch.Tensor, normals: torch.Tensor, voxel: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Average points and normals per cubic voxel of side ``voxel`` (same units).

    ``(N, 3)``, ``(N, 3)`` -> ``(M, 3)``, ``(M, 3)`` with unit normals, ``M <= N``.
    """
    key = torch.floor(points / voxel).long()
    key = key - key.min(dim=0).values
    dims = key.max(dim=0).values + 1
    flat = (key[:, 0] * dims[1] + key[:, 1]) * dims[2] + key[:, 2]
    uniq, inv = torch.unique(flat, return_inverse=True)
    count = torch.zeros(uniq.shape[0], dtype=points.dtype, device=points.device).index_add_(
        0, inv, torch.ones_like(points[:, 0])
    )
    p = torch.zeros(uniq.shape[0], 3, dtype=points.dtype, device=points.device).index_add_(0, inv, points)
    n = torch.zeros_like(p).index_add_(0, inv, normals)
    return p / count.unsqueeze(1), torch.nn.functional.normalize(n, dim=1)


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
        config: ``voxel_mm``, ``poisson_cell_mm``, depth bounds, trimming settings.
        watertight: override ``config.watertight``.

    Returns:
        the mesh in metres (same frame as the points) and statistics (depth, counts,
        whether it is closed: edge- and vertex-manifold without boundary edges).
    """
    if points.shape[0] < 10:
        raise ReconError(f"Poisson meshing needs at least 10 oriented points, got {points.shape[0]}")
    watertight = config.watertight if watertight is None else watertight
    p_mm, n = voxel_average(points.double() * 1000.0, normals.double(), config.voxel_mm)
    extent = float((p_mm.max(dim=0).values - p_mm.min(dim=0).values).max())
    depth = poisson_depth(extent, config.poisson_cell_mm, config.poisson_min_depth, config.poisson_max_depth)
    pcd = o3d.geometry.PointCloud()
    pcd.points = o3d.utility.Vector3dVector(p_mm.cpu().numpy())
    pcd.normals = o3d.utility.Vector3dVector(n.cpu().numpy())
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
