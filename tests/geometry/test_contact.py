"""Order statistics of the contact rules: percentile and zero level against numpy."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from tactile_slam.geometry.contact import colour_distance, gel_visible, order_statistic, percentile, zero_level


def _rows(kind: str, n: int, dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    """``(4, n)`` test rows: continuous values, heavy ties, or one constant."""
    g = torch.Generator().manual_seed(n)
    if kind == "ties":
        x = torch.randint(0, 4, (4, n), generator=g).to(dtype)
    elif kind == "constant":
        x = torch.full((4, n), -2.5, dtype=dtype)
    else:
        x = torch.randn(4, n, generator=g, dtype=dtype).cumsum(1)
    return x.to(device)


@pytest.mark.parametrize("kind", ["continuous", "ties", "constant"])
@pytest.mark.parametrize("n", [1, 2, 3, 101, 4096])
@pytest.mark.parametrize("q", [0.0, 10.0, 50.0, 85.0, 99.9, 100.0])
def test_percentile_matches_numpy(kind, n, q, dtype, device):
    """numpy's default (linear) percentile, row by row, to the dtype's rounding."""
    x = _rows(kind, n, dtype, device)
    got = percentile(x, q)
    assert got.shape == (4,) and got.dtype == dtype and got.device == x.device
    want = np.percentile(x.cpu().double().numpy(), q, axis=1)
    tol = 1e-12 if dtype == torch.float64 else 1e-5
    np.testing.assert_allclose(got.cpu().double().numpy(), want, rtol=tol, atol=tol)


def test_percentile_interpolates_between_neighbours():
    """Crafted row: P85 of 0..20 sits at position 17 exactly, P87.5 halfway 17.5."""
    x = torch.arange(21, dtype=torch.float64)[torch.randperm(21)][None]
    assert float(percentile(x, 85.0)) == 17.0
    assert float(percentile(x, 87.5)) == 17.5
    # a repeated value at the lower neighbour: the upper neighbour is that value again
    y = torch.tensor([[0.0, 1.0, 1.0, 5.0]], dtype=torch.float64)  # position 1.5 of 3
    assert float(percentile(y, 50.0)) == 1.0


@pytest.mark.parametrize("changed_fraction", [0.0, 0.3, 0.9, 0.96, 1.0])
def test_zero_level_subtracts_the_free_median(changed_fraction, dtype, device):
    """The lower median of the pixels outside ``changed`` (numpy on the free values);
    below 5% free pixels, the 85th percentile of the whole frame."""
    g = torch.Generator().manual_seed(3)
    h = torch.randn(3, 24, 32, generator=g, dtype=dtype).cumsum(-1).to(device)
    changed = (torch.rand(3, 24, 32, generator=g) < changed_fraction).to(device)
    changed[1] = False  # one frame fully free, whatever the fraction
    out = zero_level(h, changed)
    assert out.shape == h.shape and out.dtype == dtype
    for i in range(3):
        flat = h[i].cpu().double().numpy().ravel()
        free = flat[~changed[i].cpu().numpy().ravel()]
        if len(free) >= 0.05 * flat.size:
            level = np.sort(free)[(len(free) - 1) // 2]  # lower median: a pixel's own value
        else:
            level = np.percentile(flat, 85.0)
        np.testing.assert_allclose((h[i] - out[i]).cpu().double().numpy(), level, rtol=1e-6, atol=1e-6)


@pytest.mark.parametrize("free_px", [0, 1, 38, 39, 40, 768])
def test_gel_visible_needs_five_percent_free_pixels(free_px, device):
    """``(B, H, W)`` -> ``(B,)``: true from 5 % of the pixels outside ``changed`` (38.4 of
    768), the rule under which :func:`zero_level` takes the free median."""
    changed = torch.ones(2, 24, 32, dtype=torch.bool, device=device)
    changed[0].view(-1)[:free_px] = False
    out = gel_visible(changed)
    assert out.shape == (2,) and out.dtype == torch.bool and out.device == changed.device
    assert out.tolist() == [free_px >= 0.05 * 768, False]
    assert gel_visible(torch.zeros(3, 4, 5, dtype=torch.bool)).tolist() == [True] * 3


def test_zero_level_median_is_exact_and_differentiable():
    """The level is one free pixel's height: the shifted frame has an exact zero there, and
    the gradient reaches that pixel (every output moves with it)."""
    h = torch.tensor([[[5.0, 1.0, 3.0, 100.0], [2.0, 4.0, -50.0, 7.0]]], dtype=torch.float64, requires_grad=True)
    changed = torch.tensor([[[False, False, False, True], [False, False, True, False]]])
    out = zero_level(h, changed)  # free: 5 1 3 2 4 7 -> lower median 3
    assert float(out[0, 0, 2].detach()) == 0.0 and float(out[0, 0, 3].detach()) == 97.0
    out.sum().backward()
    grad = torch.ones_like(h)
    grad[0, 0, 2] -= 8.0  # d/dh of sum(h - h[0, 0, 2])
    assert torch.equal(h.grad, grad)


def test_colour_distance_matches_numpy(device):
    """Euclidean BGR distance of uint8 or float images to a float background (per frame
    or shared), float32, against numpy in float64."""
    g = torch.Generator().manual_seed(5)
    img = torch.randint(0, 256, (2, 6, 7, 3), generator=g, dtype=torch.uint8)
    bg = torch.rand(6, 7, 3, generator=g) * 255
    want = np.linalg.norm(img.double().numpy() - bg.double().numpy(), axis=-1)
    for x, b in ((img, bg), (img.float(), bg), (img, bg.expand(2, 6, 7, 3))):
        got = colour_distance(x.to(device), b.to(device))
        assert got.shape == (2, 6, 7) and got.dtype == torch.float32
        np.testing.assert_allclose(got.cpu().double().numpy(), want, rtol=1e-6, atol=1e-4)
    assert float(colour_distance(bg[None], bg).abs().max()) == 0.0


def test_order_statistic_values_gradients_and_bad_input(device):
    """Each row's k-th smallest value (numpy's sort as the oracle), the gradient on the
    selected entry only, and a clear error for k outside the row or a tensor not 2-D."""
    g = torch.Generator().manual_seed(7)
    x = torch.randn(3, 50, generator=g, dtype=torch.float64).to(device).requires_grad_()
    for k in (0, 17, 49):
        got = order_statistic(x, k)
        np.testing.assert_array_equal(got.detach().cpu().numpy(), np.sort(x.detach().cpu().numpy(), axis=1)[:, k])
    order_statistic(x, 17).sum().backward()
    assert torch.equal(x.grad.sum(1), torch.ones(3, dtype=torch.float64, device=x.device))
    assert int((x.grad != 0).sum()) == 3
    for bad_x, k in ((x.detach(), 50), (x.detach(), -1), (x.detach()[0], 3), (x.detach()[None], 3)):
        with pytest.raises(ValueError, match="order_statistic"):
            order_statistic(bad_x, k)
