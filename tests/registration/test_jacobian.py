import cv2
import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from tactile_slam.registration.jacobian import (
    euler_to_matrix,
    jacobian_analytic,
    jacobian_autograd,
    sobel_at,
    sobel_at_patches,
)
from tactile_slam.registration.normalflow import prepare_reference

from .surfaces import as_dtype, bumpy, frames


def test_euler_matches_scipy(dtype):
    angles = torch.tensor([[0.3, -0.2, 1.1], [-2.0, 0.5, 0.01]], dtype=dtype)
    expected = Rotation.from_euler("xyz", angles.double().numpy()).as_matrix()
    tol = 1e-6 if dtype == torch.float32 else 1e-12
    assert np.allclose(euler_to_matrix(angles).double().numpy(), expected, atol=tol)


def test_euler_gradcheck():
    angles = torch.tensor([[0.3, -0.2, 1.1]], dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(euler_to_matrix, (angles,))


@pytest.mark.parametrize("fn", [sobel_at, sobel_at_patches])
def test_sobel_at_matches_opencv_including_borders(device, dtype, fn):
    g = torch.Generator().manual_seed(0)
    maps = torch.rand((2, 12, 15, 3), generator=g, dtype=torch.float64)
    maps[1] = maps[1].flip(0)  # a different second map: each batch element is filtered on its own
    idx = torch.tensor([[0, 1, 14, 16, 50, 95, 179], [179, 3, 0, 44, 60, 61, 178]])  # corners, edges, interior
    got = fn(maps.to(device, dtype), idx.to(device)).cpu().double()
    assert got.shape == (2, 7, 3, 2) and got.dtype == torch.float64
    for b, ch in ((0, 0), (0, 1), (0, 2), (1, 0), (1, 2)):
        img = maps[b, :, :, ch].numpy()
        dx = cv2.Sobel(img, cv2.CV_64F, 1, 0, ksize=5, scale=2**-7).ravel()[idx[b].numpy()]
        dy = cv2.Sobel(img, cv2.CV_64F, 0, 1, ksize=5, scale=2**-7).ravel()[idx[b].numpy()]
        tol = 1e-5 if dtype == torch.float32 else 1e-12
        assert np.allclose(got[b, :, ch, 0].numpy(), dx, atol=tol)
        assert np.allclose(got[b, :, ch, 1].numpy(), dy, atol=tol)


def _random_inputs(n=64, seed=0, device="cpu"):
    """Channels-first points, normals ``(2, 3, n)`` and derivatives ``(2, 3, 2, n)``."""
    g = torch.Generator().manual_seed(seed)
    p = (torch.rand((2, 3, n), generator=g, dtype=torch.float64) - 0.5) * 1e-2
    nrm = torch.nn.functional.normalize(torch.rand((2, 3, n), generator=g, dtype=torch.float64) + 0.5, dim=1)
    d = torch.randn((2, 3, 2, n), generator=g, dtype=torch.float64) * 300.0
    return p.to(device), nrm.to(device), d.to(device)


def test_autograd_equals_analytic(device):
    p, n, d = _random_inputs(device=device)
    ja = jacobian_analytic(p, n, d)
    jg = jacobian_autograd(p, n, d)
    assert ja.shape == jg.shape == (2, 5, 3, 64)
    assert torch.allclose(ja, jg, atol=1e-10, rtol=1e-10)


def test_analytic_matches_the_closed_form_per_sample():
    """J = D Jw + [n]x | 0, written out with numpy for one sample (method.md 4.3)."""
    p, n, d = _random_inputs(n=5)
    P, N, D = p[1, :, 3].numpy(), n[1, :, 3].numpy(), d[1, :, :, 3].numpy()
    jw = np.array([[0, P[2], -P[1], 1, 0], [-P[2], 0, P[0], 0, 1]])
    skew = np.array([[0, -N[2], N[1]], [N[2], 0, -N[0]], [-N[1], N[0], 0]])
    expected = D @ jw + np.hstack([skew, np.zeros((3, 2))])
    assert np.allclose(jacobian_analytic(p, n, d)[1, :, :, 3].numpy().T, expected, atol=1e-12)


def test_sobel_at_filters_only_the_pixels_neighbourhood():
    """Pixels away from every border: the cropped filter equals the full image's."""
    g = torch.Generator().manual_seed(1)
    maps = torch.rand((1, 40, 50, 3), generator=g, dtype=torch.float64)
    idx = torch.tensor([[10 * 50 + 12, 11 * 50 + 30, 20 * 50 + 47, 37 * 50 + 13]])  # near the right/bottom edge too
    got = sobel_at(maps, idx)
    ref = sobel_at_patches(maps, idx)
    assert torch.allclose(got, ref, atol=1e-12)
    img = maps[0, :, :, 1].numpy()
    dy = cv2.Sobel(img, cv2.CV_64F, 0, 1, ksize=5, scale=2**-7).ravel()[idx[0].numpy()]
    assert np.allclose(got[0, :, 1, 1].numpy(), dy, atol=1e-12)


def test_analytic_gradcheck():
    p, n, d = _random_inputs(n=4)
    args = tuple(x.clone().requires_grad_(True) for x in (p, n, d))
    assert torch.autograd.gradcheck(jacobian_analytic, args)


def _true_normals(surf, x, y):
    """Gel normals of the analytic surface at metric (x, y), by autograd on f."""
    x = x.clone().requires_grad_(True)
    y = y.clone().requires_grad_(True)
    fx, fy = torch.autograd.grad(surf(x, y).sum(), (x, y))
    return torch.nn.functional.normalize(torch.stack([-fx, -fy, torch.ones_like(fx)], -1), dim=-1)


def test_jacobian_matches_finite_differences_of_the_true_residual():
    """r(delta) = R^T N(proj(dT P)) - N(proj(P)) on the analytic surface, whose central
    differences at delta = 0 are what the Sobel-based Jacobian approximates."""
    surf = bumpy(2)
    ref = as_dtype(frames(surf, [torch.eye(4, dtype=torch.float64)]), torch.float64)
    prep = prepare_reference(ref, dtype=torch.float64)
    keep = prep.valid[0] & (prep.points[0, :, 2] < -0.3e-3)  # away from the contact rim
    P = prep.points[0][keep]
    n0 = _true_normals(surf, P[:, 0], P[:, 1])
    eps = (1e-4, 1e-4, 1e-4, 1e-6, 1e-6)
    cols = []
    for j, e in enumerate(eps):
        r = []
        for sgn in (1.0, -1.0):
            d = torch.zeros(5, dtype=torch.float64)
            d[j] = sgn * e
            R = euler_to_matrix(d[None, :3])[0]
            q = P @ R.T + torch.cat([d[3:], d[:1] * 0])
            r.append(_true_normals(surf, q[:, 0], q[:, 1]) @ R - n0)
        cols.append((r[0] - r[1]) / (2 * e))
    fd = torch.stack(cols, dim=-1)  # (K, 3, 5)
    J = prep.levels[-1].jacobian_t[0].view(5, 3, -1).permute(2, 1, 0)[keep]
    err = (fd - J).norm(dim=(0, 1)) / fd.norm(dim=(0, 1))
    assert (err < 0.1).all(), err


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("kind", ["analytic", "autograd"])
def test_prepared_jacobian_kinds_agree(kind, dtype):
    """The Jacobian is computed in the working dtype: the two kinds agree to its rounding."""
    from tactile_slam.config import NormalFlowConfig

    ref = as_dtype(frames(bumpy(0), [torch.eye(4, dtype=torch.float64)]), dtype)
    a = prepare_reference(ref, NormalFlowConfig(jacobian="analytic", n_samples=500))
    b = prepare_reference(ref, NormalFlowConfig(jacobian=kind, n_samples=500))
    tol = 1e-9 if dtype == torch.float64 else 1e-5
    for name in ("jtj", "jacobian_t", "ata_full"):
        x, y = getattr(a.levels[-1], name), getattr(b.levels[-1], name)
        assert x.dtype == (torch.float64 if name != "jacobian_t" else dtype)
        assert torch.allclose(x, y, rtol=tol, atol=tol * float(x.abs().max())), name
