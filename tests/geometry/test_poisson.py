import pytest
import torch

from tactile_slam.geometry.poisson import _dct2, _idct2, integrate_exact, integrate_legacy

from .surfaces import central_gradients, gaussian_dent, grid, sinusoid, spherical_cap


def _depth(h):
    return float(h.max() - h.min())


def _err(est, true):
    return float(((est - est.mean()) - (true - true.mean())).abs().max())


class TestIntegrateExact:
    def test_plane_exact(self):
        r, c = grid()
        h = 0.1 * c - 0.05 * r
        assert _err(integrate_exact(central_gradients(h))[0], h) < 1e-9

    def test_gaussian_within_005px(self):
        h = gaussian_dent(10.0, 20.0)
        est = integrate_exact(central_gradients(h))[0]
        assert _err(est, h) < 0.05

    def test_spherical_cap_within_03px(self):
        h = spherical_cap(49.76, 12.0)
        est = integrate_exact(central_gradients(h))[0]
        assert _err(est, h) < 0.3
        assert abs(_depth(est) - 12.0) / 12.0 < 0.02

    def test_sinusoid_within_2_percent(self):
        h = sinusoid(3.0, 40.0)
        est = integrate_exact(central_gradients(h))[0]
        assert _err(est, h) / _depth(h) < 0.02

    def test_random_smooth_field(self):
        g = torch.Generator().manual_seed(0)
        coarse = torch.randn(1, 1, 12, 16, generator=g, dtype=torch.float64) * 5
        h = torch.nn.functional.interpolate(coarse, size=(240, 320), mode="bicubic", align_corners=True)[0, 0]
        est = integrate_exact(central_gradients(h))[0]
        assert _err(est, h) / _depth(h) < 0.02

    def test_legacy_is_too_deep(self):
        """The public SDK's solver over-estimates depth (the reason it is not the default)."""
        h = gaussian_dent(10.0, 20.0)
        assert _depth(integrate_legacy(central_gradients(h))[0]) > 1.05 * _depth(h)

    def test_batch_equals_single(self, device):
        g = torch.cat([central_gradients(gaussian_dent()), central_gradients(spherical_cap())]).to(device)
        batch = integrate_exact(g)
        for i in range(2):
            torch.testing.assert_close(batch[i], integrate_exact(g[i : i + 1])[0])

    def test_dtype(self, device, dtype):
        g = central_gradients(spherical_cap()).to(device, dtype)
        out = integrate_exact(g)
        assert out.dtype == dtype and out.shape == (1, 240, 320)
        ref = integrate_exact(central_gradients(spherical_cap()).to(device))
        torch.testing.assert_close(out.double(), ref, atol=1e-3, rtol=0)

    def test_cpu_backend_matches_matrix_backend(self):
        x = torch.randn(2, 24, 32, dtype=torch.float64)
        y = x.clone().requires_grad_(True)  # forces the matrix-product path
        torch.testing.assert_close(_dct2(x), _dct2(y).detach())
        torch.testing.assert_close(_idct2(_dct2(x)), x)

    def test_gradcheck(self):
        g = torch.randn(1, 6, 8, 2, dtype=torch.float64, requires_grad=True)
        assert torch.autograd.gradcheck(integrate_exact, (g,))

    def test_bad_shape(self):
        with pytest.raises(ValueError, match=r"\(B, H, W, 2\)"):
            integrate_exact(torch.zeros(240, 320, 2))
