"""The batched 5x5 Gauss-Newton solve against per-pair Cholesky (scipy)."""

import numpy as np
import pytest
from scipy.linalg import cho_factor, cho_solve

from tactile_slam.registration.normalflow import _solve


def _spd(rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray]:
    a = rng.normal(size=(n, 5, 12))
    return a @ a.transpose(0, 2, 1), rng.normal(size=(n, 5))


def _oracle(m: np.ndarray, b: np.ndarray) -> np.ndarray:
    return cho_solve(cho_factor(m), b)


@pytest.mark.parametrize("n", [1, 3, 64])
@pytest.mark.parametrize("damping", [0.0, 0.1])
def test_batched_solve_equals_per_pair_cholesky(n, damping):
    ata, atb = _spd(np.random.default_rng(n), n)
    ridge = np.zeros_like(ata)
    delta, solved = _solve(ata, atb, ridge, damping)
    assert delta.shape == (n, 5) and solved.shape == (n,) and solved.all()
    for i in range(n):
        d = np.diag(ata[i])
        floor = np.r_[np.full(3, d[:3].mean()), np.full(2, d[3:].mean())]  # per block, in its own unit
        want = _oracle(ata[i] + damping * np.diag(d + 1e-3 * floor), atb[i])
        np.testing.assert_allclose(delta[i], want, rtol=1e-9, atol=1e-12)


@pytest.mark.parametrize("bad", ["zero", "nan"])
def test_unsolvable_pair_fails_alone(bad):
    """A flat contact's all-zero equations (no ridge can help) or NaN ones: that pair gets
    a zero step and ``solved`` False; the others are solved as if alone."""
    ata, atb = _spd(np.random.default_rng(7), 4)
    ata[2] = 0.0 if bad == "zero" else np.nan
    delta, solved = _solve(ata, atb, np.zeros_like(ata), 0.0)
    assert solved.tolist() == [True, True, False, True]
    assert (delta[2] == 0).all()
    for i in (0, 1, 3):
        np.testing.assert_allclose(delta[i], _oracle(ata[i], atb[i]), rtol=1e-9, atol=1e-12)


def test_ridge_keeps_an_unobservable_direction_at_zero():
    """Rank-4 equations (nothing constrains the fifth unknown): with the ridge the step
    along it is 0, not NaN, and the rest solves the observable block."""
    rng = np.random.default_rng(3)
    a = rng.normal(size=(4, 12))
    ata = np.zeros((1, 5, 5))
    ata[0, :4, :4] = a @ a.T
    atb = np.zeros((1, 5))
    atb[0, :4] = rng.normal(size=4)
    ridge = 1e-12 * ata[0].diagonal().max() * np.eye(5)[None]
    delta, solved = _solve(ata, atb, ridge, 0.0)
    assert solved[0] and delta[0, 4] == 0.0
    np.testing.assert_allclose(delta[0, :4], _oracle(ata[0, :4, :4], atb[0, :4]), rtol=1e-6)
