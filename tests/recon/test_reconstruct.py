"""End-to-end reconstruction of a known shape with perfect poses; outputs and errors."""

from __future__ import annotations

import numpy as np
import open3d as o3d
import pytest
import torch

from tactile_slam.config import Config
from tactile_slam.recon import ReconError, reconstruct, reconstruct_groups
from tests.recon.recon_oracle import sphere_chamfer_mm, sphere_keyframes

RADIUS_MM = 3.0


def small_config() -> Config:
    cfg = Config()
    cfg.recon.poisson_min_depth = 6  # 0.1 mm cells on this 6 mm sphere
    cfg.recon.poisson_max_depth = 6
    return cfg


@pytest.fixture(scope="module")
def sphere_scan():
    cfg = small_config()
    kfs, poses = sphere_keyframes(cfg, radius_mm=RADIUS_MM, depth_mm=0.8, n=30)
    return cfg, kfs, poses, reconstruct(kfs, poses, cfg)


def test_sphere_with_perfect_poses_is_accurate_and_watertight(sphere_scan):
    _, kfs, _, res = sphere_scan
    assert res.stats["keyframes"] == 30 and 1 < res.stats["coverage_keyframes"] <= 30
    for mesh in (res.fused_mesh, res.mesh):
        acc, comp = sphere_chamfer_mm(mesh.vertices.numpy(), mesh.faces.numpy(), RADIUS_MM)
        assert acc < 0.05
    acc, comp = sphere_chamfer_mm(res.mesh.vertices.numpy(), res.mesh.faces.numpy(), RADIUS_MM)
    assert 0.5 * (acc + comp) < 0.05  # method.md 8.3 step 7
    o3 = res.mesh.to_open3d()
    assert o3.is_edge_manifold(allow_boundary_edges=False) and o3.is_vertex_manifold()
    assert o3.euler_poincare_characteristic() == 2  # one closed genus-0 surface
    assert res.stats["mesh_closed"] and o3.is_watertight()
    # outward normals on both meshes
    for mesh in (res.fused_mesh, res.mesh):
        assert float(np.median((mesh.normals * mesh.vertices).sum(1).numpy())) > 0


def test_outputs_written_in_metres(sphere_scan, tmp_path):
    _, _, _, res = sphere_scan
    paths = res.save(tmp_path, render=False)
    assert sorted(p.name for p in paths.values()) == ["mesh.ply", "mesh_fused.ply"]
    m = o3d.io.read_triangle_mesh(str(tmp_path / "mesh.ply"))
    r = np.linalg.norm(np.asarray(m.vertices), axis=1)
    assert abs(float(np.median(r)) - RADIUS_MM / 1000) < 5e-5
    assert len(m.triangles) == res.mesh.n_faces


def test_groups_and_dict_poses(sphere_scan):
    cfg, kfs, poses, _ = sphere_scan
    cfg = small_config()
    cfg.recon.poisson = False
    groups = {kf.id: (0 if kf.id < 8 else 1) for kf in kfs}
    res = reconstruct(kfs, {kf.id: poses[i] for i, kf in enumerate(kfs)}, cfg, groups=groups)
    assert res.group == 1 and res.stats["keyframes"] == 22 and res.mesh is None
    all_res = reconstruct_groups(kfs, poses, cfg, groups)
    assert sorted(all_res) == [0, 1]
    assert all_res[0].stats["keyframes"] == 8


def test_clear_errors(sphere_scan):
    cfg, kfs, poses, _ = sphere_scan
    with pytest.raises(ReconError, match="no keyframes"):
        reconstruct([], torch.zeros(0, 4, 4, dtype=torch.float64), cfg)
    with pytest.raises(ReconError, match="at least 2 keyframes"):
        reconstruct(kfs[:1], poses[:1], cfg)
    with pytest.raises(ReconError, match=r"shape \(3, 4, 4\)"):
        reconstruct(kfs[:3], poses[:2], cfg)
    with pytest.raises(ReconError, match="no pose for keyframe"):
        reconstruct(kfs[:3], {0: poses[0]}, cfg)
    bad = poses[:3].clone()
    bad[1, 0, 3] = float("nan")
    with pytest.raises(ReconError, match="NaN"):
        reconstruct(kfs[:3], bad, cfg)
    with pytest.raises(ReconError, match="unknown group"):
        reconstruct(kfs[:3], poses[:3], cfg, group=5)
    assert issubclass(ReconError, ValueError)


def test_touches_too_small_to_fuse_are_named():
    """Light presses (~110 px of contact, boundary-weighted area ~1 px) are never coverage
    keyframes: the error says why instead of failing later in the fusion."""
    cfg = small_config()
    kfs, poses = sphere_keyframes(cfg, radius_mm=RADIUS_MM, depth_mm=0.1, n=3)
    assert all(bool(k.frame.contact.any()) for k in kfs)
    with pytest.raises(ReconError, match="no coverage keyframe.*too small to fuse"):
        reconstruct(kfs, poses, cfg)
