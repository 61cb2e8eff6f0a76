"""Watertight re-meshing (method.md 8.3)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from tactile_slam.config import ReconConfig
from tactile_slam.recon import ReconError, poisson_mesh
from tactile_slam.recon.meshing import bin_sums, pack_keys, poisson_depth, voxel_average, voxel_keys, voxel_sums


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
    q, m, voxel = voxel_average(p, n, 0.05)
    assert voxel == 0.05
    assert q.shape == (2, 3) and m.shape == (2, 3)
    order = torch.argsort(q[:, 0])
    torch.testing.assert_close(q[order[0]], torch.tensor([0.02, 0.015, 0.025], dtype=dtype))
    torch.testing.assert_close(m[order[0]], torch.tensor([0.0, 2**-0.5, 2**-0.5], dtype=dtype))
    torch.testing.assert_close(m.norm(dim=1), torch.ones(2, dtype=dtype))


def test_voxel_budget_coarsens_exactly():
    """Over the point budget the voxel grows to an integer multiple; the result is the
    plain average of the original points at that voxel, computed here independently."""
    rng = np.random.default_rng(0)
    p = torch.from_numpy(rng.uniform(0, 2.0, size=(20_000, 3)))
    p[:, 2] = 0.1 * torch.sin(3 * p[:, 0])  # a wavy sheet
    n = torch.nn.functional.normalize(torch.from_numpy(rng.normal(size=(20_000, 3))), dim=1)
    full, _, _ = voxel_average(p, n, 0.05)
    q, m, voxel = voxel_average(p, n, 0.05, max_points=len(full) // 5)
    assert len(q) <= len(full) // 5 < len(full)
    factor = voxel / 0.05
    assert factor > 2 and abs(factor - round(factor)) < 1e-9
    keys = np.floor(p.numpy() / voxel).astype(np.int64)
    _, inv = np.unique(keys, axis=0, return_inverse=True)
    inv = inv.reshape(-1)
    expected = np.stack([np.bincount(inv, p.numpy()[:, k]) for k in range(3)], 1) / np.bincount(inv)[:, None]
    normals = np.stack([np.bincount(inv, n.numpy()[:, k]) for k in range(3)], 1)
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    order_q = np.lexsort(np.floor(q.numpy() / voxel).T)
    order_e = np.lexsort(np.floor(expected / voxel).T)
    np.testing.assert_allclose(q.numpy()[order_q], expected[order_e], atol=1e-12)
    np.testing.assert_allclose(m.numpy()[order_q], normals[order_e], atol=1e-12)


def test_voxel_average_of_parts_equals_the_whole(dtype):
    """Parts (one per keyframe, uneven, one empty), the chunked sums and a unit scale
    give the single tensor's averages, in the same order."""
    rng = np.random.default_rng(1)
    p = torch.from_numpy(rng.uniform(-3.0, 3.0, size=(5000, 3))).to(dtype)
    n = torch.nn.functional.normalize(torch.from_numpy(rng.normal(size=(5000, 3))), dim=1).to(dtype)
    q, m, voxel = voxel_average(p * 1000.0, n, 400.0)
    cuts = [0, 7, 7, 1800, 4999, 5000]
    parts = [(p[a:b], n[a:b]) for a, b in zip(cuts[:-1], cuts[1:])]
    q2, m2, voxel2 = voxel_average([x for x, _ in parts], [y for _, y in parts], 400.0, scale=1000.0)
    assert voxel2 == voxel and q2.shape == q.shape and len(q) < len(p)
    tol = 1e-9 if dtype == torch.float64 else 1e-3
    torch.testing.assert_close(q2, q, atol=tol, rtol=0)
    torch.testing.assert_close(m2, m, atol=tol * 1e-3, rtol=1e-4)
    sums = voxel_sums([(p[:100], torch.ones(100, 1, dtype=dtype)), (p[100:], torch.ones(4900, 1, dtype=dtype))],
                      0.4, chunk=64)
    assert float(sums.sum()) == 5000 and len(sums) == len(q)


@pytest.mark.parametrize("spread", [3, 10_000])
def test_bin_sums_match_independent_sums(dtype, spread):
    """A compact cloud (summed in a dense box) and a spread one (through a sort) give
    the distinct voxels, sorted as their packed keys, with the sums of their values."""
    rng = np.random.default_rng(3)
    idx = torch.from_numpy(rng.integers(-spread, spread + 1, size=(4000, 3)))
    values = torch.from_numpy(rng.normal(size=(4000, 2))).to(dtype)
    keys, sums = bin_sums(idx, values)
    uniq, inv = np.unique(idx.numpy(), axis=0, return_inverse=True)
    inv = inv.reshape(-1)
    expected = np.stack([np.bincount(inv, values[:, c].double().numpy()) for c in range(2)], 1)
    np.testing.assert_array_equal(keys.numpy(), pack_keys(torch.from_numpy(uniq)).numpy())  # lexicographic
    tol = 1e-12 if dtype == torch.float64 else 1e-4
    np.testing.assert_allclose(sums.double().numpy(), expected, atol=tol, rtol=0)
    k0, s0 = bin_sums(idx[:0], values[:0])
    assert k0.shape == (0,) and s0.shape == (0, 2)


def test_voxel_keys_order_and_range():
    """Keys sort as the voxel indices (i, j, k) lexicographically, negative indices
    included; points beyond 2^20 voxels from the origin are refused."""
    rng = np.random.default_rng(2)
    p = torch.from_numpy(rng.uniform(-50.0, 50.0, size=(2000, 3)))
    idx = np.floor(p.numpy() / 0.7).astype(np.int64)
    order = np.argsort(voxel_keys(p, 0.7).numpy(), kind="stable")
    np.testing.assert_array_equal(idx[order], idx[np.lexsort(idx.T[::-1])])
    with pytest.raises(ReconError, match="voxels"):
        voxel_keys(torch.tensor([[0.0, 0.0, 2.0**20 * 0.5]], dtype=torch.float64), 0.5)
    with pytest.raises(ReconError, match="NaN"):
        voxel_keys(torch.tensor([[0.0, float("nan"), 0.0]]), 0.5)
    with pytest.raises(ReconError, match="no points"):
        voxel_average([torch.zeros(0, 3)], [torch.zeros(0, 3)], 0.5)
    with pytest.raises(ReconError, match="no points"):
        voxel_average([], [], 0.5)


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


@pytest.mark.parametrize("threads", [-1, 2])
def test_poisson_threads_give_the_same_surface(threads):
    """One Poisson thread (the default: Open3D's multi-threaded solver can segfault) and
    several give the same closed sphere to within a small fraction of a cell."""
    cfg = ReconConfig(poisson_min_depth=6, poisson_max_depth=6)
    p, n = sphere_samples(20000, 3e-3)
    one, s_one = poisson_mesh(p, n, cfg)
    many, s_many = poisson_mesh(p, n, ReconConfig(poisson_min_depth=6, poisson_max_depth=6, poisson_threads=threads))
    assert s_one["closed"] and s_many["closed"] and s_one["poisson_depth"] == s_many["poisson_depth"]
    for mesh in (one, many):
        assert np.abs(mesh.vertices.norm(dim=1).numpy() * 1000 - 3.0).mean() < 0.02


@pytest.mark.parametrize("bad", [0, -2, 1.5, True])
def test_poisson_threads_must_be_valid(bad):
    p, n = sphere_samples(2000, 3e-3)
    with pytest.raises(ReconError, match="poisson_threads"):
        poisson_mesh(p, n, ReconConfig(poisson_threads=bad))


def test_point_budget_must_be_positive():
    p = torch.rand(100, 3, dtype=torch.float64)
    n = torch.nn.functional.normalize(torch.rand(100, 3, dtype=torch.float64), dim=1)
    for bad in (0, -5):
        with pytest.raises(ReconError, match="poisson_max_points"):
            voxel_average(p, n, 0.05, max_points=bad)


def test_point_budget_coarsens_voxel_and_cell_together():
    """Over the budget the voxel and the Poisson cell grow by the same factor (a lower
    depth); the coarse surface still lies on the sphere to within a fraction of a cell."""
    p, n = sphere_samples(40000, 3e-3)
    fine, s_fine = poisson_mesh(p, n, ReconConfig())
    coarse, s_coarse = poisson_mesh(p, n, ReconConfig(poisson_max_points=3000))
    assert s_fine["voxel_mm"] == 0.05 and s_fine["poisson_points"] > 3000
    assert s_coarse["poisson_points"] <= 3000 and s_coarse["voxel_mm"] > 0.1
    factor = s_coarse["voxel_mm"] / 0.05
    assert s_coarse["poisson_depth"] == poisson_depth(6.0, 0.1 * factor, 6, 11) < s_fine["poisson_depth"]
    assert s_coarse["closed"] and coarse.n_faces < fine.n_faces / 2
    r = coarse.vertices.norm(dim=1).numpy() * 1000
    assert np.abs(r - 3.0).mean() < 0.1 * 0.1 * factor


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
