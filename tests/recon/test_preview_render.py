"""Incremental preview surface and offscreen rendering."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from matplotlib.image import imread

from tactile_slam.config import Config
from tactile_slam.recon import ReconError
from tactile_slam.recon.mesh import MeshError, TriMesh
from tactile_slam.recon.preview import PreviewSurface
from tactile_slam.recon.render import render_points, render_views
from tests.recon.recon_oracle import sphere_keyframes

RADIUS_MM = 3.0


@pytest.fixture(scope="module")
def scan():
    cfg = Config()
    kfs, poses = sphere_keyframes(cfg, radius_mm=RADIUS_MM, depth_mm=0.8, n=10)
    return cfg, kfs, poses


def test_preview_accumulates_on_the_surface(scan):
    cfg, kfs, poses = scan
    prev = PreviewSurface(cfg, voxel_mm=0.1, stride=2)
    sizes = []
    for kf, pose in zip(kfs, poses):
        prev.add(kf, pose)
        sizes.append(prev.points()[0].shape[0])
    assert len(prev) == 10 and all(b >= a for a, b in zip(sizes, sizes[1:])) and sizes[-1] > sizes[0]
    p, n = prev.points()
    r = p.norm(dim=1).numpy() * 1000
    assert np.abs(r - RADIUS_MM).mean() < 0.02
    assert float((n * p).sum(1).min()) > 0  # outward
    # voxel means stay inside their voxels' neighbourhood: no two closer than half a voxel
    # on average, i.e. no duplicate stacking
    assert p.shape[0] < sum(int(kf.frame.contact.sum()) for kf in kfs) / 4 + 1


def test_preview_update_poses_moves_points(scan):
    cfg, kfs, poses = scan
    prev = PreviewSurface(cfg)
    for kf, pose in zip(kfs[:3], poses[:3]):
        prev.add(kf, pose)
    before = prev.points()[0]
    shift = torch.eye(4, dtype=torch.float64)
    shift[2, 3] = 1e-3
    prev.update_poses({kf.id: shift @ pose for kf, pose in zip(kfs[:3], poses[:3])})
    after = prev.points()[0]
    assert after.shape[0] > 0
    assert abs(float(after[:, 2].mean() - before[:, 2].mean()) - 1e-3) < 1e-4


def test_preview_outputs_and_errors(scan, tmp_path):
    cfg, kfs, poses = scan
    prev = PreviewSurface(cfg)
    with pytest.raises(ReconError, match="empty"):
        prev.save_ply(tmp_path / "p.ply")
    with pytest.raises(ReconError, match="finite"):
        prev.add(kfs[0], torch.full((4, 4), float("nan")))
    with pytest.raises(ReconError):
        PreviewSurface(cfg, voxel_mm=0.0)
    prev.add(kfs[0], poses[0])
    assert prev.save_ply(tmp_path / "p.ply").stat().st_size > 0
    img = imread(prev.save_png(tmp_path / "p.png"))
    assert img.ndim == 3 and img[..., :3].std() > 0.01


def test_render_mesh_png(tmp_path):
    # an open square made of two triangles, seen from four views
    v = torch.tensor([[0, 0, 0], [1e-3, 0, 0], [0, 1e-3, 0], [1e-3, 1e-3, 0]], dtype=torch.float64)
    f = torch.tensor([[0, 2, 1], [2, 3, 1]])
    mesh = TriMesh(vertices=v, faces=f, normals=torch.tensor([[0, 0, -1.0]] * 4, dtype=torch.float64))
    img = imread(render_views(mesh, tmp_path / "m.png", size_px=400))
    assert img.shape[:2] == (400, 400) and img[..., :3].std() > 0.01
    with pytest.raises(MeshError):
        render_views(TriMesh(v, f[:0], v), tmp_path / "x.png")
    with pytest.raises(MeshError):
        render_points(np.zeros((0, 3)), np.zeros((0, 3)), tmp_path / "y.png")
