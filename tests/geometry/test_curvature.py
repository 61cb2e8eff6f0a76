import math

import kornia
import numpy as np
import pytest
import torch

from tactile_slam.geometry.curvature import curvature, divergence, gaussian_curvature, normals_from_gradients

from .surfaces import central_gradients, gaussian_dent, grid, sinusoid


def test_normals_unit_and_direction():
    g = torch.tensor([[[[0.5, -0.25]]]])
    n = normals_from_gradients(g)
    torch.testing.assert_close(torch.linalg.vector_norm(n, dim=-1), torch.ones(1, 1, 1))
    # (-gx, -gy, 1) direction: toward the object (+z)
    assert n[0, 0, 0, 0] < 0 and n[0, 0, 0, 1] > 0 and n[0, 0, 0, 2] > 0


def test_normals_match_numpy_over_slopes_and_dtypes(dtype, device):
    """``(-gx, -gy, 1) / |.|`` against numpy in float64, from flat to near-vertical slopes
    (|g| up to 1e4: the rsqrt stays finite and the normal lies down), to the dtype's
    rounding."""
    g = torch.Generator().manual_seed(0)
    mag = torch.logspace(-8, 4, 60, dtype=torch.float64)
    ang = torch.rand(60, generator=g, dtype=torch.float64) * 6.283
    grads = torch.stack([mag * ang.cos(), mag * ang.sin()], -1).reshape(3, 4, 5, 2)
    n = normals_from_gradients(grads.to(dtype=dtype, device=device))
    assert n.shape == (3, 4, 5, 3) and n.dtype == dtype and n.device.type == device.type
    raw = np.concatenate([-grads.numpy(), np.ones((3, 4, 5, 1))], -1)
    want = raw / np.linalg.norm(raw, axis=-1, keepdims=True)
    tol = 1e-14 if dtype == torch.float64 else 3e-7
    np.testing.assert_allclose(n.cpu().double().numpy(), want, rtol=0, atol=tol)


def test_normals_gradcheck():
    g = (torch.randn(1, 3, 4, 2, dtype=torch.float64) * 2).requires_grad_()
    assert torch.autograd.gradcheck(normals_from_gradients, (g,))


def test_divergence_of_paraboloid_is_constant():
    r, c = grid()
    h = 0.01 * (r**2 + c**2)  # Laplacian = 0.04
    d = divergence(central_gradients(h))
    torch.testing.assert_close(d[0, 5:-5, 5:-5], torch.full_like(d[0, 5:-5, 5:-5], 0.04))


def test_curvature_masked_and_clipped(dtype):
    r, c = grid(dtype)
    h = 1.0 * (r**2 + c**2)  # Laplacian 4 -> clipped to 0.7
    g = central_gradients(h)
    mask = torch.zeros(1, 240, 320, dtype=torch.bool)
    mask[:, 50:100, 60:120] = True
    lap = curvature(g, mask)
    assert lap.dtype == dtype
    assert (lap[~mask] == 0).all()
    torch.testing.assert_close(lap[mask], torch.full_like(lap[mask], 0.7))


def test_curvature_batch(device):
    g = torch.randn(3, 24, 32, 2, device=device) * 0.1
    m = torch.ones(3, 24, 32, dtype=torch.bool, device=device)
    out = curvature(g, m)
    assert out.shape == (3, 24, 32)
    torch.testing.assert_close(out[1:2], curvature(g[1:2], m[1:2]))


def test_curvature_gradcheck():
    g = torch.randn(1, 8, 9, 2, dtype=torch.float64, requires_grad=True) * 0.01
    m = torch.ones(1, 8, 9, dtype=torch.bool)
    assert torch.autograd.gradcheck(lambda x: curvature(x, m, clip=10.0), (g,))


@pytest.mark.parametrize("ksize", [3, 5, 9])
def test_curvature_window_equals_full_image(ksize, dtype, device):
    """Only a window around the batch's contact is computed; every pixel equals the
    full-image computation (divergence, blur over the whole image, mask, clip), to the
    rounding of a convolution over another size, and outside contact exactly zero: contact
    in the interior, against each border and in a corner, one pixel of contact, a frame
    without contact beside frames with it, and a batch with none at all."""
    g = torch.randn(5, 40, 56, 2, generator=torch.Generator().manual_seed(ksize), dtype=dtype).to(device) * 0.3
    m = torch.zeros(5, 40, 56, dtype=torch.bool, device=device)
    m[0, 12:20, 20:31] = True
    m[1, 0:6, 40:56] = True
    m[2, 30:40, 0:3] = True
    m[3, 39, 55] = True
    full = kornia.filters.gaussian_blur2d(divergence(g).unsqueeze(1), (ksize, ksize), (1.1, 1.1),
                                          border_type="reflect").squeeze(1)
    want = torch.where(m, full, torch.zeros_like(full)).clamp(-0.7, 0.7)
    tol = 1e-12 if dtype == torch.float64 else 1e-6
    for i in range(5):
        got = curvature(g[i:i + 1], m[i:i + 1], ksize)
        torch.testing.assert_close(got, want[i:i + 1], rtol=0, atol=tol)
        assert (got[~m[i:i + 1]] == 0).all()
    torch.testing.assert_close(curvature(g, m, ksize), want, rtol=0, atol=tol)
    assert (curvature(g, torch.zeros_like(m), ksize) == 0).all()


class TestGaussianCurvature:
    """``2 sign(K) sqrt(|K|)`` of the blurred Hessian determinant (the loop features' other map)."""

    def test_paraboloid_equals_the_laplacian(self, dtype):
        """A bump with equal principal curvatures: the map is its Laplacian (the scale
        both maps share)."""
        r, c = grid(dtype)
        g = central_gradients(0.01 * (r**2 + c**2))  # h_xx = h_yy = 0.02, Laplacian 0.04
        m = torch.ones(1, 240, 320, dtype=torch.bool)
        inner = (slice(None), slice(5, -5), slice(5, -5))
        torch.testing.assert_close(gaussian_curvature(g, m)[inner], curvature(g, m)[inner])
        torch.testing.assert_close(gaussian_curvature(g, m)[inner], torch.full((1, 230, 310), 0.04, dtype=dtype))

    def test_a_line_vanishes_and_a_saddle_does_not(self):
        """Ridges (one principal curvature zero) leave no trace, unlike in the Laplacian; a
        saddle, which the Laplacian does not see, is negative."""
        r, c = grid()
        m = torch.ones(1, 240, 320, dtype=torch.bool)
        inner = (slice(None), slice(5, -5), slice(5, -5))
        ridges = central_gradients(3.0 * torch.sin(2 * math.pi * c / 40.0))
        assert gaussian_curvature(ridges, m)[inner].abs().max() < 1e-12
        assert curvature(ridges, m)[inner].abs().max() > 0.05
        saddle = central_gradients(0.01 * (c**2 - r**2))  # h_xx = -h_yy = 0.02, K = -4e-4
        torch.testing.assert_close(gaussian_curvature(saddle, m)[inner], torch.full((1, 230, 310), -0.04,
                                                                                     dtype=torch.float64))
        assert curvature(saddle, m)[inner].abs().max() < 1e-12

    def test_rotation_invariant(self):
        """A quarter turn of the surface turns the map with it (the slopes turn as vectors)."""
        h = gaussian_dent() + sinusoid(amp=1.0)
        m = torch.ones(1, 240, 240, dtype=torch.bool)
        h = h[:, 40:280]  # square, so a quarter turn keeps the size
        turned = torch.rot90(h, 1, (0, 1))
        a = gaussian_curvature(central_gradients(h), m, clip=10.0)
        b = gaussian_curvature(central_gradients(turned), m, clip=10.0)
        inner = (slice(None), slice(5, -5), slice(5, -5))
        torch.testing.assert_close(torch.rot90(a, 1, (1, 2))[inner], b[inner], rtol=0, atol=1e-12)

    @pytest.mark.parametrize("ksize", [3, 5])
    def test_window_equals_full_image(self, ksize, dtype, device):
        """Computed in a window around the contact, every pixel is the full-image result
        masked (rounding of a convolution over another size), and zero outside contact."""
        g = torch.randn(3, 40, 56, 2, generator=torch.Generator().manual_seed(ksize), dtype=dtype).to(device) * 0.3
        m = torch.zeros(3, 40, 56, dtype=torch.bool, device=device)
        m[0, 12:20, 20:31] = True
        m[1, 0:6, 40:56] = True
        full = gaussian_curvature(g, torch.ones_like(m), ksize, clip=100.0)
        want = torch.where(m, full, torch.zeros_like(full)).clamp(-0.7, 0.7)
        tol = 1e-10 if dtype == torch.float64 else 1e-5
        for i in range(3):
            got = gaussian_curvature(g[i:i + 1], m[i:i + 1], ksize)
            torch.testing.assert_close(got, want[i:i + 1], rtol=0, atol=tol)
            assert (got[~m[i:i + 1]] == 0).all()
        assert gaussian_curvature(g, m, ksize).shape == (3, 40, 56)


@pytest.mark.parametrize("shape,ksize", [((1, 8), 5), ((8, 1), 1), ((2, 2), 5), ((4, 4), 9)])
def test_images_too_small_for_the_blur_are_refused(shape, ksize):
    """Before: torch.gradient's or kornia's padding error from deep inside."""
    g = torch.zeros(1, *shape, 2)
    c = torch.ones(1, *shape, dtype=torch.bool)
    for fn in (curvature, gaussian_curvature):
        with pytest.raises(ValueError, match=f"image is too small for curvature with a {ksize}-px blur"):
            fn(g, c, ksize=ksize)


def test_the_smallest_images_the_blur_allows_work():
    g = torch.zeros(1, 3, 3, 2)
    c = torch.ones(1, 3, 3, dtype=torch.bool)
    assert (curvature(g, c, ksize=5) == 0).all() and (gaussian_curvature(g, c, ksize=5) == 0).all()
