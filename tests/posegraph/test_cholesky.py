"""Multifrontal block Cholesky against dense solves."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from tactile_slam.posegraph.cholesky import BlockCholesky, FactorError, _lower_schur_update


def _random_block_spd(n: int, edges: np.ndarray, seed: int = 0, b: int = 6):
    """Blocks of J^T J for random per-edge Jacobians, in the slot order of a symmetric pattern."""
    rng = np.random.default_rng(seed)
    dense = np.eye(n * b) * 0.5
    for a, c in edges:
        Ja, Jc = rng.normal(size=(b, b)), rng.normal(size=(b, b))
        sa, sc = slice(a * b, (a + 1) * b), slice(c * b, (c + 1) * b)
        dense[sa, sa] += Ja.T @ Ja
        dense[sc, sc] += Jc.T @ Jc
        dense[sa, sc] += Ja.T @ Jc
        dense[sc, sa] += Jc.T @ Ja
    keys = sorted({(k, k) for k in range(n)} | {(a, c) for a, c in edges} | {(c, a) for a, c in edges})
    rows = np.array([k[0] for k in keys])
    cols = np.array([k[1] for k in keys])
    blocks = np.stack([dense[r * b:(r + 1) * b, c * b:(c + 1) * b] for r, c in keys])
    return dense, rows, cols, blocks


@pytest.mark.parametrize("n, leaf", [(1, 32), (7, 32), (150, 8), (250, 32)])
def test_matches_dense_solve(n, leaf):
    rng = np.random.default_rng(n)
    coords = np.cumsum(rng.normal(size=(n, 3)), axis=0)
    chain = [(k, k + 1) for k in range(n - 1)]
    extra = [tuple(sorted(rng.choice(n, 2, replace=False))) for _ in range(n // 2)] if n > 2 else []
    edges = np.array(sorted(set(chain) | set(extra)), dtype=np.int64).reshape(-1, 2)
    dense, rows, cols, blocks = _random_block_spd(n, edges)
    ch = BlockCholesky(n, rows, cols, coords, leaf_size=leaf)
    assert sorted(ch.perm.tolist()) == list(range(n))
    ch.factor(blocks)
    rhs = rng.normal(size=n * 6)
    assert np.allclose(ch.solve(rhs), np.linalg.solve(dense, rhs), rtol=1e-8, atol=1e-10)


def test_large_fronts_take_the_panelled_lower_update():
    """A graph with many long edges has fronts whose boundary exceeds the one-product size
    (the row-panel Schur update runs); the solve still matches the dense one."""
    n = 400
    rng = np.random.default_rng(5)
    coords = np.cumsum(rng.normal(size=(n, 3)), axis=0)
    chain = [(k, k + 1) for k in range(n - 1)]
    extra = [tuple(sorted(rng.choice(n, 2, replace=False))) for _ in range(n)]
    edges = np.array(sorted(set(chain) | set(extra)), dtype=np.int64)
    dense, rows, cols, blocks = _random_block_spd(n, edges, seed=5)
    ch = BlockCholesky(n, rows, cols, coords, leaf_size=16)
    assert max(6 * f.bnd.size for f in ch.fronts) >= 256
    ch.factor(blocks)
    rhs = rng.normal(size=n * 6)
    assert np.allclose(ch.solve(rhs), np.linalg.solve(dense, rhs), rtol=1e-8, atol=1e-10)


@pytest.mark.parametrize("m", [10, 300, 1001])
def test_lower_schur_update_matches_the_full_product_below_the_diagonal(m):
    rng = np.random.default_rng(m)
    F = torch.from_numpy(rng.normal(size=(m, m)))
    L = torch.from_numpy(rng.normal(size=(m, 37)))
    want = F - L @ L.T
    got = _lower_schur_update(F.clone(), L)
    lower = torch.ones(m, m, dtype=torch.bool).tril()
    torch.testing.assert_close(got[lower], want[lower], rtol=1e-12, atol=1e-12)


def test_disconnected_components_and_degenerate_coordinates():
    n = 90
    edges = np.array([(k, k + 1) for k in range(n - 1) if k % 30 != 29])  # three chains
    dense, rows, cols, blocks = _random_block_spd(n, edges, seed=4)
    ch = BlockCholesky(n, rows, cols, np.zeros((n, 3)), leaf_size=4)  # all nodes at one point
    ch.factor(blocks)
    rhs = np.arange(n * 6, dtype=float)
    assert np.allclose(ch.solve(rhs), np.linalg.solve(dense, rhs))


def test_not_positive_definite_raises():
    n = 3
    edges = np.array([(0, 1), (1, 2)])
    _, rows, cols, blocks = _random_block_spd(n, edges)
    blocks[rows == cols] = -np.eye(6)
    ch = BlockCholesky(n, rows, cols, np.zeros((n, 3)))
    with pytest.raises(FactorError, match="positive definite"):
        ch.factor(blocks)
