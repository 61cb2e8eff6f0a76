"""Fusion of coverage keyframes and grid triangulation (method.md 8.1-8.2)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.ndimage import distance_transform_edt

from tests.recon.recon_oracle import sphere_keyframes
from tactile_slam.config import Config
from tactile_slam.geometry.frame import FrameBuilder
from tactile_slam.recon import ReconError, fuse, merge_surfaces
from tactile_slam.recon.fusion import grid_normals
from tactile_slam.recon.mesh import grid_faces, vertex_normals
from tactile_slam.tracking.keyframe import Keyframe

CFG = Config()
S = CFG.sensor.m_per_px
H, W = CFG.sensor.shape


def flat_keyframe(kf_id: int, r0, r1, c0, c1, device="cpu") -> Keyframe:
    contact = torch.zeros(1, H, W, dtype=torch.bool)
    contact[0, r0:r1, c0:c1] = True
    frame = FrameBuilder(CFG).from_gradients(torch.zeros(1, H, W, 2), contact=contact)
    return Keyframe(id=kf_id, session=0, frame=frame.to(device), new_session=False,
                    prev_T_kf=torch.eye(4, dtype=torch.float64))


def shifted(dx_px=0.0, dz_m=0.0) -> torch.Tensor:
    T = torch.eye(4, dtype=torch.float64)
    T[0, 3] = dx_px * S
    T[2, 3] = dz_m
    return T


def weights_np(r0, r1, c0, c1) -> np.ndarray:
    m = np.zeros((H, W), bool)
    m[r0:r1, c0:c1] = True
    d = distance_transform_edt(np.pad(m, 1))[1:-1, 1:-1]
    return 0.5 * (np.tanh(d / (H / 60) - 3) + 1) * m


def test_grid_faces_winding_and_count(device):
    mask = torch.zeros(4, 5, dtype=torch.bool, device=device)
    mask[1:3, 1:4] = True  # 2 x 3 block -> 2 x (1 x 2) quads -> 4 triangles
    f = grid_faces(mask)
    assert f.shape == (4, 3) and f.dtype == torch.int64
    # vertices of the masked pixels, row-major, flat
    rr, cc = torch.nonzero(mask, as_tuple=True)
    v = torch.stack([cc.double(), rr.double(), torch.zeros_like(rr, dtype=torch.float64)], 1)
    n = vertex_normals(v, f)
    torch.testing.assert_close(n, torch.tensor([0.0, 0.0, -1.0], dtype=torch.float64, device=device).expand_as(n))
    assert grid_faces(torch.zeros(3, 3, dtype=torch.bool)).shape == (0, 3)


def test_grid_normals_face_outward(dtype):
    ys, xs = torch.meshgrid(torch.arange(8, dtype=dtype), torch.arange(9, dtype=dtype), indexing="ij")
    pts = torch.stack([xs, ys, 0.5 * xs], -1)  # plane z = x / 2
    n = grid_normals(pts)
    expected = torch.tensor([0.5, 0.0, -1.0], dtype=dtype) / (1.25**0.5)
    torch.testing.assert_close(n, expected.expand_as(n))
    assert n.shape == (8, 9, 3)


def test_fused_point_is_weighted_mean_of_surfaces(device):
    """Two flat keyframes 0.1 mm apart in depth, side by side: each fused point is
    ((W_a + 1e-8) z_a + W_b z_b) / (W_a + 1e-8 + W_b), computed here independently."""
    box = (60, 180, 60, 260)
    kfs = [flat_keyframe(0, *box, device=device), flat_keyframe(1, *box, device=device)]
    poses = torch.stack([shifted(), shifted(dx_px=100, dz_m=1e-4)])
    fused = fuse(kfs, poses, CFG)
    assert [f.id for f in fused] == [0, 1]
    wa = weights_np(*box)
    wb = np.zeros_like(wa)
    wb[:, 100:] = wa[:, :-100]  # b's weights seen at a's pixels (b is 100 px to the right)
    m = wa > 0
    expected = (wb[m] * 1e-4) / (wa[m] + 1e-8 + wb[m])
    got = fused[0].points[:, 2].cpu().numpy()
    np.testing.assert_allclose(got, expected, atol=2e-7)
    assert torch.isfinite(fused[0].points).all() and torch.isfinite(fused[0].normals).all()


def test_gate_blocks_distant_surfaces(device):
    box = (60, 180, 60, 260)
    kfs = [flat_keyframe(0, *box, device=device), flat_keyframe(1, *box, device=device)]
    poses = torch.stack([shifted(), shifted(dx_px=100, dz_m=2e-3)])  # 2 mm deeper
    cfg = Config()
    cfg.recon.fusion_gate_mm = 1.0
    fused = fuse(kfs, poses, cfg)
    assert float(fused[0].points[:, 2].abs().max()) == 0.0
    cfg.recon.fusion_gate_mm = 3.0
    assert float(fuse(kfs, poses, cfg)[0].points[:, 2].abs().max()) > 1e-3
    cfg.recon.fusion_gate_mm = 0.0
    with pytest.raises(ReconError, match="fusion_gate_mm"):
        fuse(kfs, poses, cfg)


def test_merged_mesh_has_no_stacked_sheets(device):
    """Overlapping keyframes contribute each surface point once."""
    box = (40, 200, 40, 280)
    kfs = [flat_keyframe(0, *box, device=device), flat_keyframe(1, *box, device=device)]
    poses = torch.stack([shifted(), shifted(dx_px=120)])
    fused = fuse(kfs, poses, CFG)
    mesh = merge_surfaces(fused)
    union = 160 * (240 + 120)
    assert mesh.n_vertices <= union
    assert mesh.n_vertices >= 0.97 * union
    # no two vertices closer than a fraction of a pixel
    v = mesh.vertices.numpy()
    from scipy.spatial import cKDTree

    d, _ = cKDTree(v).query(v, k=2)
    assert d[:, 1].min() > 0.5 * S
    assert torch.allclose(mesh.normals[:, 2], torch.tensor(-1.0, dtype=torch.float64))


def test_fused_sphere_points_lie_on_sphere():
    cfg = Config()
    kfs, poses = sphere_keyframes(cfg, radius_mm=3.0, depth_mm=0.8, n=12)
    fused = fuse(kfs, poses, cfg)
    pts = torch.cat([f.points for f in fused]).numpy() * 1000
    err = np.abs(np.linalg.norm(pts, axis=1) - 3.0)
    assert err.mean() < 0.01 and err.max() < 0.05
    nrm = torch.cat([f.normals for f in fused]).numpy()
    inner = (nrm * pts / np.linalg.norm(pts, axis=1, keepdims=True)).sum(1)
    assert np.median(inner) > 0.99  # outward normals
