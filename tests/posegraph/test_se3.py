"""SE(3) helpers against pypose and finite differences."""

from __future__ import annotations

import math

import pypose as pp
import pytest
import torch

from tactile_slam.posegraph import se3


def _random_poses(n: int, dtype, device, sigma: float = 1.0) -> torch.Tensor:
    gen = torch.Generator().manual_seed(0)
    xi = torch.randn(n, 6, generator=gen, dtype=torch.float64) * sigma
    return se3.exp(xi).to(dtype=dtype, device=device)


class TestExpLog:
    def test_smoke_and_shapes(self, device, dtype):
        xi = torch.zeros(2, 3, 6, dtype=dtype, device=device)
        T = se3.exp(xi)
        assert T.shape == (2, 3, 4, 4)
        assert torch.allclose(T, torch.eye(4, dtype=dtype, device=device).expand(2, 3, 4, 4))
        assert se3.log(T).shape == (2, 3, 6)

    def test_against_pypose(self, device, dtype):
        gen = torch.Generator().manual_seed(1)
        xi = torch.randn(200, 6, generator=gen, dtype=torch.float64) * 1.2
        ref = pp.se3(xi).Exp()
        T = se3.exp(xi.to(dtype=dtype, device=device))
        tol = 1e-12 if dtype == torch.float64 else 1e-5
        assert torch.allclose(T.cpu().double(), se3.from_pypose(ref), atol=tol)
        assert torch.allclose(se3.log(se3.from_pypose(ref).to(dtype=dtype, device=device)).cpu().double(),
                              ref.Log().tensor(), atol=tol * 10)

    def test_round_trip_small_and_large_angles(self, device):
        xi = torch.tensor([[1e-9, 0, 0, 1e-10, 0, 0], [0.1, 0.2, 0.3, 0, 0, math.pi - 1e-6],
                           [0.0, 0.0, 0.0, 0.0, 3.0, 0.0]], dtype=torch.float64, device=device)
        assert torch.allclose(se3.log(se3.exp(xi)), xi, atol=1e-9)

    def test_half_turn(self):
        T = torch.diag(torch.tensor([1.0, -1.0, -1.0, 1.0], dtype=torch.float64))
        xi = se3.log(T)
        assert torch.allclose(xi[3:].abs(), torch.tensor([math.pi, 0, 0], dtype=torch.float64))
        assert torch.allclose(se3.exp(xi), T, atol=1e-12)


class TestAlgebra:
    def test_inverse(self, device, dtype):
        T = _random_poses(10, dtype, device)
        eye = torch.eye(4, dtype=dtype, device=device).expand(10, 4, 4)
        assert torch.allclose(T @ se3.inverse(T), eye, atol=1e-5 if dtype == torch.float32 else 1e-12)

    def test_adjoint_against_pypose(self, device):
        T = _random_poses(20, torch.float64, device)
        xi = torch.randn(20, 6, dtype=torch.float64, device=device)
        ref = se3.to_pypose(T.cpu()).Adj(pp.se3(xi.cpu())).tensor()
        assert torch.allclose((se3.adjoint(T) @ xi[..., None]).squeeze(-1).cpu(), ref, atol=1e-12)

    def test_adjoint_identity(self, device):
        T = _random_poses(5, torch.float64, device)
        xi = torch.randn(5, 6, dtype=torch.float64, device=device) * 0.3
        lhs = se3.exp((se3.adjoint(T) @ xi[..., None]).squeeze(-1))
        rhs = T @ se3.exp(xi) @ se3.inverse(T)
        assert torch.allclose(lhs, rhs, atol=1e-12)

    def test_quaternion_round_trip(self, device):
        T = _random_poses(100, torch.float64, device, sigma=2.0)
        half = torch.diag(torch.tensor([-1.0, -1.0, 1.0], dtype=torch.float64, device=device))
        R = torch.cat([T[:, :3, :3], half[None]])
        q = se3.rotmat_to_quat(R)
        assert torch.allclose(q.norm(dim=-1), torch.ones(101, dtype=torch.float64, device=device))
        assert (q[:, 3] >= 0).all()
        assert torch.allclose(se3.quat_to_rotmat(q), R, atol=1e-12)


class TestJacobians:
    def test_right_jacobian_inv_finite_difference(self):
        gen = torch.Generator().manual_seed(2)
        xi = torch.randn(6, 6, generator=gen, dtype=torch.float64)
        xi[0] *= 1e-7
        J = se3.right_jacobian_inv(xi)
        eps = 1e-6
        num = torch.zeros_like(J)
        for k in range(6):
            d = torch.zeros(6, dtype=torch.float64)
            d[k] = eps
            num[:, :, k] = (se3.log(se3.exp(xi) @ se3.exp(d)) - se3.log(se3.exp(xi) @ se3.exp(-d))) / (2 * eps)
        assert torch.allclose(J, num, atol=1e-7)

    @pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
    @pytest.mark.parametrize("theta", [0.0, 1e-6, 1e-3, 0.0499, 0.0501, 0.5, 2.0, 3.1])
    def test_right_jacobian_inv_series_oracle(self, theta, dtype):
        """Against the inverse of ``Jr = sum_n (-ad)^n / (n+1)!`` (60 terms, float64), on both
        sides of the small-angle switch and up to nearly pi."""
        gen = torch.Generator().manual_seed(5)
        axis = torch.randn(8, 3, generator=gen, dtype=torch.float64)
        xi = torch.cat([torch.randn(8, 3, generator=gen, dtype=torch.float64) * 0.02,
                        axis / axis.norm(dim=-1, keepdim=True) * theta], -1)
        ad = torch.zeros(8, 6, 6, dtype=torch.float64)
        ad[:, :3, :3] = ad[:, 3:, 3:] = se3.skew(xi[:, 3:])
        ad[:, :3, 3:] = se3.skew(xi[:, :3])
        term, Jr = torch.eye(6, dtype=torch.float64).expand(8, 6, 6), torch.zeros(8, 6, 6, dtype=torch.float64)
        for n in range(60):
            Jr = Jr + term
            term = term @ (-ad) / (n + 2)
        J = se3.right_jacobian_inv(xi.to(dtype))
        assert J.dtype == dtype and J.shape == (8, 6, 6)
        tol = 1e-12 if dtype == torch.float64 else 1e-5
        assert torch.allclose(J.double(), torch.linalg.inv(Jr), atol=tol, rtol=0)

    def test_between_jacobians_finite_difference(self):
        gen = torch.Generator().manual_seed(3)
        Z, Ti, Tj = (se3.exp(torch.randn(4, 6, generator=gen, dtype=torch.float64)) for _ in range(3))
        e, Ji, Jj = se3.between_jacobians(Z, Ti, Tj)
        assert torch.allclose(e, se3.between_error(Z, Ti, Tj))
        assert all(torch.equal(x, y) for x, y in zip(se3.between_jacobians(Z, Ti, Tj, e), (e, Ji, Jj)))
        eps = 1e-6
        for J, which in ((Ji, 0), (Jj, 1)):
            num = torch.zeros_like(J)
            for k in range(6):
                d = torch.zeros(6, dtype=torch.float64)
                d[k] = eps
                args_p = [Ti, Tj]
                args_m = [Ti, Tj]
                args_p[which] = args_p[which] @ se3.exp(d)
                args_m[which] = args_m[which] @ se3.exp(-d)
                num[:, :, k] = (se3.between_error(Z, *args_p) - se3.between_error(Z, *args_m)) / (2 * eps)
            assert torch.allclose(J, num, atol=1e-7)

    def test_gradcheck_exp(self):
        xi = (torch.randn(3, 6, dtype=torch.float64) * 0.5).requires_grad_()
        assert torch.autograd.gradcheck(se3.exp, (xi,))


class TestCheckPose:
    @pytest.mark.parametrize("bad, msg", [
        (torch.eye(3), "shape"),
        (torch.full((4, 4), float("nan")), "NaN"),
        (torch.diag(torch.tensor([2.0, 1.0, 1.0, 1.0])), "orthonormal"),
        (torch.diag(torch.tensor([-1.0, 1.0, 1.0, 1.0])), "reflection"),
        (torch.tensor([[1.0, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [1, 0, 0, 1]]), "last row"),
    ])
    def test_rejects(self, bad, msg):
        with pytest.raises(se3.PoseError, match=msg):
            se3.check_pose(bad)

    def test_accepts_batch(self):
        T = _random_poses(3, torch.float32, "cpu")
        out = se3.check_pose(T)
        assert out.dtype == torch.float64 and out.shape == (3, 4, 4)


def test_shifts_xy_are_pure_translations_along_the_four_axis_directions():
    T = se3.shifts_xy(0.5e-3)
    assert T.shape == (4, 4, 4) and T.dtype == torch.float64
    torch.testing.assert_close(T[:, :3, :3], torch.eye(3, dtype=torch.float64).expand(4, 3, 3))
    torch.testing.assert_close(T[:, :3, 3], torch.tensor([[0.5e-3, 0, 0], [-0.5e-3, 0, 0], [0, 0.5e-3, 0],
                                                          [0, -0.5e-3, 0]], dtype=torch.float64))
    torch.testing.assert_close(T[:, 3], torch.tensor([0, 0, 0, 1.0], dtype=torch.float64).expand(4, 4))
