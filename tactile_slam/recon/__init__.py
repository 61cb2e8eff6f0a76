"""Reconstruction: keyframe surface fusion and watertight meshing (method.md section 8).

``reconstruct(keyframes, start_T_kf, config) -> ReconResult(fused_mesh, mesh, stats)``;
``ReconResult.save(dir)`` writes ``mesh_fused.ply``, ``mesh.ply`` (metres, the group's
start frame) and ``mesh.png``.
"""

from tactile_slam.recon.fusion import FusedKeyframe, ReconError, fuse, merge_surfaces
from tactile_slam.recon.mesh import MeshError, TriMesh
from tactile_slam.recon.meshing import poisson_mesh
from tactile_slam.recon.preview import PreviewSurface
from tactile_slam.recon.reconstruct import ReconResult, reconstruct, reconstruct_groups

__all__ = [
    "FusedKeyframe", "MeshError", "PreviewSurface", "ReconError", "ReconResult", "TriMesh", "fuse", "merge_surfaces",
    "poisson_mesh", "reconstruct", "reconstruct_groups",
]
