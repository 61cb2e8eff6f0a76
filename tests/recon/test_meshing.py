"""Watertight re-meshing (method.md 8.3)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from tactile_slam.config import ReconConfig
from tactile_slam.recon import ReconError, poisson_mesh
from tactile_slam.recon.meshing import poisson_depth, voxel_average


def sphere_samples(n: int, radius_m: float, seed: int = 0, hemisphere: bool = False):
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    if hemisphere:
        d[:, 2] = np.abs(d[:, 2])
    return torch.from_numpy(d * radius_m), torch.from_numpy(d.copy())


def test_voxel_average(dtype):
    p = torch.tensor([[0.01, 0.01, 0.01], [0.03, 0.02, 0.04], [1.01, 0.0, 0.0]], dtype=dtype)
    n = torch.tensor([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0]], dtype=dtype)
    q, m = voxel_average(p, n, 0.05)
    assert q.shape == (2, 3) and m.shape == (2, 3)
    order = torch.argsort(q[:, 0])
    torch.testing.assert_close(q[order[0]], torch.tensor([0.02, 0.015, 0.025], dtype=dtype))
    torch.testing.assert_close(m[order[0]], torch.tensor([0.0, 2**-0.5, 2**-0.5], dtype=dtype))
    torch.testing.assert_close(m.norm(dim=1), torch.ones(2, dtype=dtype))


def test_poisson_depth_clamps():
    assert poisson_depth(20.0, 0.1, 8, 11) == 8  # 220 cells -> 2^8
    assert poisson_depth(100.0, 0.1, 8, 11) == 11  # 1100 cells -> 2^11
    assert poisson_depth(500.0, 0.1, 8, 11) == 11
    assert poisson_depth(1.0, 0.1, 8, 11) == 8


def test_poisson_sphere_is_watertight_and_accurate():
    cfg = ReconConfig(poisson_min_depth=6, poisson_max_depth=6)
    p, n = sphere_samples(20000, 3e-3)
    mesh, stats = poisson_mesh(p, n, cfg, watertight=True)
    o3 = mesh.to_open3d()
    assert stats["closed"] and o3.is_edge_manifold(allow_boundary_edges=False)
    assert o3.euler_poincare_characteristic() == 2  # closed genus 0 (is_watertight: test_reconstruct)
    r = mesh.vertices.norm(dim=1).numpy() * 1000
    assert np.abs(r - 3.0).mean() < 0.02
    # outward normals
    assert float((mesh.normals * mesh.vertices).sum(1).min()) > 0


def test_trimmed_partial_scan_stays_near_data():
    cfg = ReconConfig(poisson_min_depth=6, poisson_max_depth=6)
    p, n = sphere_samples(20000, 3e-3, hemisphere=True)
    closed, _ = poisson_mesh(p, n, cfg, watertight=True)
    open_, stats = poisson_mesh(p, n, cfg, watertight=False)
    assert not stats["closed"]
    z_open = open_.vertices[:, 2].numpy() * 1000
    assert z_open.min() > -cfg.trim_distance_mm - 0.05  # nothing invented far below the data
    assert closed.vertices[:, 2].min() * 1000 < -1.0  # the closed surface bulges there


def test_too_few_points():
    with pytest.raises(ReconError, match="at least 10"):
        poisson_mesh(torch.zeros(3, 3, dtype=torch.float64), torch.ones(3, 3, dtype=torch.float64), ReconConfig())
