"""Batched SE(3) on homogeneous matrices for the pose graph (float64, metres).

Poses are ``(..., 4, 4)`` float64 matrices ``a_T_b``. Tangent vectors are ``(..., 6)`` ordered
**[translation, rotation]** = ``[rho, phi]``, pypose's ``se3`` order (GTSAM orders them
[rotation, translation]); every 6-vector and 6x6 block in this package (noise sigmas,
information matrices, Jacobians) uses this order. Perturbations are on the right:
``T <- T . Exp(delta)``.

Exp/Log/adjoint are written in plain batched torch and tested against pypose's LieTensor
``Exp``/``Log``/``Adj``: the solver calls them thousands of times on small batches, and each
pypose op carries about 0.1 ms of Python dispatch (an autograd ``Function`` binding its
signature), which dominated incremental updates. pypose stays the reference (its
``optim.LM`` checks the solver) and the exchange type (:func:`to_pypose`, :func:`from_pypose`).
"""

from __future__ import annotations

from functools import lru_cache

import pypose as pp
import torch


class PoseError(ValueError):
    """A pose is malformed (wrong shape, not finite, not a rigid transform)."""


def skew(v: torch.Tensor) -> torch.Tensor:
    """Cross-product matrices ``(..., 3, 3)`` of vectors ``(..., 3)``."""
    x, y, z = v.unbind(-1)
    o = torch.zeros_like(x)
    return torch.stack([o, -z, y, z, o, -x, -y, x, o], dim=-1).reshape(v.shape[:-1] + (3, 3))


def check_pose(T: torch.Tensor) -> torch.Tensor:
    """Validate homogeneous matrices ``(..., 4, 4)`` and return them as float64.

    Raises :class:`PoseError` when the input is not ``(..., 4, 4)``, is not finite, or is
    not a rigid transform (rotation not orthonormal within 1e-6 or a reflection, last row not
    ``[0, 0, 0, 1]``).
    """
    T = torch.as_tensor(T, dtype=torch.float64)
    if T.ndim < 2 or T.shape[-2:] != (4, 4):
        raise PoseError(f"pose must have shape (..., 4, 4), got {tuple(T.shape)}")
    if not torch.isfinite(T).all():
        raise PoseError("pose contains NaN or inf")
    if T.numel():
        R = T[..., :3, :3]
        eye = torch.eye(3, dtype=T.dtype, device=T.device)
        bottom = torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=T.dtype, device=T.device)
        if (R.transpose(-1, -2) @ R - eye).abs().amax().item() > 1e-6:
            raise PoseError("pose rotation is not orthonormal")
        if (torch.linalg.det(R) < 0).any():
            raise PoseError("pose rotation is a reflection (det < 0)")
        if (T[..., 3, :] - bottom).abs().amax().item() > 1e-9:
            raise PoseError("pose last row must be [0, 0, 0, 1]")
    return T


def to_pypose(T: torch.Tensor) -> pp.LieTensor:
    """pypose SE3 LieTensor ``(..., 7)`` = ``[t, qx, qy, qz, qw]`` of matrices ``(..., 4, 4)``."""
    return pp.SE3(torch.cat([T[..., :3, 3], rotmat_to_quat(T[..., :3, :3])], dim=-1))


def from_pypose(X: pp.LieTensor) -> torch.Tensor:
    """Homogeneous matrices ``(..., 4, 4)`` of pypose SE3 LieTensors ``(..., 7)``."""
    x = X.tensor() if isinstance(X, pp.LieTensor) else X
    T = torch.zeros(x.shape[:-1] + (4, 4), dtype=x.dtype, device=x.device)
    T[..., :3, :3] = quat_to_rotmat(x[..., 3:])
    T[..., :3, 3] = x[..., :3]
    T[..., 3, 3] = 1.0
    return T


def inverse(T: torch.Tensor) -> torch.Tensor:
    """Inverse rigid transforms ``(..., 4, 4)``."""
    Rt = T[..., :3, :3].transpose(-1, -2)
    return torch.cat([torch.cat([Rt, -(Rt @ T[..., :3, 3:])], -1), T[..., 3:, :]], -2)


def tilt_deg(a_T_b: torch.Tensor) -> torch.Tensor:
    """Out-of-plane part of relative poses ``(..., 4, 4)`` (or their rotations
    ``(..., 3, 3)``): the angle in degrees between the two frames' z axes (the sensor
    axis), ``(...)``; a turn about z alone has none."""
    cos = a_T_b[..., 2, 2].clamp(-1.0, 1.0)
    return torch.rad2deg(torch.arccos(cos))


def twist_deg(a_T_b: torch.Tensor) -> torch.Tensor:
    """In-plane part of relative poses ``(..., 4, 4)`` (or their rotations ``(..., 3, 3)``):
    the angle in degrees, in [0, 180], of the rotation left about the sensor axis once the
    tilt is taken out (swing-twist split, ``2 atan2(|q_z|, q_w)``); ``(...)``."""
    R = a_T_b[..., :3, :3]
    return torch.rad2deg(torch.atan2(R[..., 1, 0] - R[..., 0, 1], R[..., 0, 0] + R[..., 1, 1]).abs())


def shifts_xy(distance_m: float) -> torch.Tensor:
    """Translations by ``distance_m`` along +x, -x, +y and -y: ``(4, 4, 4)`` float64 (the
    nearby starts of the tracker's keyframe check and of the loop ambiguity check)."""
    T = torch.eye(4, dtype=torch.float64).repeat(4, 1, 1)
    T[:, :2, 3] = torch.tensor([[1.0, 0.0], [-1.0, 0.0], [0.0, 1.0], [0.0, -1.0]], dtype=torch.float64) * distance_m
    return T


def exp(xi: torch.Tensor) -> torch.Tensor:
    """``Exp`` of se3 vectors ``(..., 6)`` [rho, phi] as matrices ``(..., 4, 4)``."""
    rho, phi = xi[..., :3], xi[..., 3:]
    K = skew(phi)
    theta2 = (phi * phi).sum(-1)[..., None, None]
    theta = theta2.sqrt()
    small = theta < 1e-4
    s = torch.where(small, torch.ones_like(theta), theta)
    a = torch.where(small, 1 - theta2 / 6, torch.sin(s) / s)
    b = torch.where(small, 0.5 - theta2 / 24, (1 - torch.cos(s)) / (s * s))
    c = torch.where(small, 1 / 6 - theta2 / 120, (s - torch.sin(s)) / (s * s * s))
    KK = K @ K
    eye = torch.eye(3, dtype=xi.dtype, device=xi.device)
    T = torch.zeros(xi.shape[:-1] + (4, 4), dtype=xi.dtype, device=xi.device)
    T[..., :3, :3] = eye + a * K + b * KK
    T[..., :3, 3] = ((eye + b * K + c * KK) @ rho[..., None]).squeeze(-1)
    T[..., 3, 3] = 1.0
    return T


def log(T: torch.Tensor) -> torch.Tensor:
    """``Log`` of rigid transforms ``(..., 4, 4)`` as se3 vectors ``(..., 6)`` [rho, phi].

    The rotation angle comes from the quaternion (``2 atan2(|v|, w)``), accurate at every
    angle up to pi.
    """
    q = rotmat_to_quat(T[..., :3, :3])
    v, w = q[..., :3], q[..., 3:]
    n = v.norm(dim=-1, keepdim=True)
    small = n < 1e-8
    scale = torch.where(small, 2.0 / w, 2.0 * torch.atan2(n, w) / torch.where(small, torch.ones_like(n), n))
    phi = v * scale
    rho = _so3_left_jacobian_inv_apply(phi, T[..., :3, 3])
    return torch.cat([rho, phi], dim=-1)


# Shepperd's four candidate quaternions (rows: x-, y-, z-, w-pivot; columns x, y, z, w) as
# a linear map of [1, m00, m01, m02, m10, m11, m12, m20, m21, m22].
_SHEPPERD = (
    (1, 1, 0, 0, 0, -1, 0, 0, 0, -1), (0, 0, 1, 0, 1, 0, 0, 0, 0, 0),
    (0, 0, 0, 1, 0, 0, 0, 1, 0, 0), (0, 0, 0, 0, 0, 0, -1, 0, 1, 0),
    (0, 0, 1, 0, 1, 0, 0, 0, 0, 0), (1, -1, 0, 0, 0, 1, 0, 0, 0, -1),
    (0, 0, 0, 0, 0, 0, 1, 0, 1, 0), (0, 0, 0, 1, 0, 0, 0, -1, 0, 0),
    (0, 0, 0, 1, 0, 0, 0, 1, 0, 0), (0, 0, 0, 0, 0, 0, 1, 0, 1, 0),
    (1, -1, 0, 0, 0, -1, 0, 0, 0, 1), (0, 0, -1, 0, 1, 0, 0, 0, 0, 0),
    (0, 0, 0, 0, 0, 0, -1, 0, 1, 0), (0, 0, 0, 1, 0, 0, 0, -1, 0, 0),
    (0, 0, -1, 0, 1, 0, 0, 0, 0, 0), (1, 1, 0, 0, 0, 1, 0, 0, 0, 1),
)


@lru_cache(maxsize=8)
def _shepperd_map(dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    """``(10, 16)`` constant: row vector ``[1, R.ravel()]`` times it gives the candidates."""
    return torch.tensor(_SHEPPERD, dtype=dtype, device=device).T.contiguous()


def rotmat_to_quat(R: torch.Tensor) -> torch.Tensor:
    """Unit quaternions ``(..., 4)`` = ``[x, y, z, w]`` with ``w >= 0`` of rotations ``(..., 3, 3)``.

    Shepperd's method: of the four algebraically equivalent formulas, each element uses the
    one with the largest pivot, so the result is accurate for every rotation angle. The four
    candidates come from one product with a constant matrix (few ops on small batches).
    """
    lead = R.shape[:-2]
    v = torch.cat([torch.ones(lead + (1,), dtype=R.dtype, device=R.device), R.reshape(lead + (9,))], -1)
    cand = (v @ _shepperd_map(R.dtype, R.device)).reshape(lead + (4, 4))
    pivot = torch.diagonal(cand, dim1=-2, dim2=-1).argmax(-1)
    q = torch.gather(cand, -2, pivot[..., None, None].expand(pivot.shape + (1, 4))).squeeze(-2)
    q = q / q.norm(dim=-1, keepdim=True)
    return torch.where(q[..., 3:] < 0, -q, q)


def quat_to_rotmat(q: torch.Tensor) -> torch.Tensor:
    """Rotation matrices ``(..., 3, 3)`` of unit quaternions ``(..., 4)`` = ``[x, y, z, w]``."""
    x, y, z, w = q.unbind(-1)
    return torch.stack([
        1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w),
        2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w),
        2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y),
    ], dim=-1).reshape(q.shape[:-1] + (3, 3))


def adjoint(T: torch.Tensor) -> torch.Tensor:
    """Adjoint matrices ``(..., 6, 6)`` of poses ``(..., 4, 4)``, tangent [rho, phi].

    ``Exp(Ad(T) xi) = T . Exp(xi) . T^-1``; ``Ad = [[R, [t]x R], [0, R]]``.
    """
    R, t = T[..., :3, :3], T[..., :3, 3]
    A = torch.zeros(T.shape[:-2] + (6, 6), dtype=T.dtype, device=T.device)
    A[..., :3, :3] = R
    A[..., 3:, 3:] = R
    A[..., :3, 3:] = skew(t) @ R
    return A


def _so3_left_jacobian_inv_coeff(phi: torch.Tensor) -> torch.Tensor:
    """``c`` in ``Jl^-1(phi) = I - K/2 + c K^2`` (``K = [phi]x``), series near 0. ``(..., 3)`` -> ``(..., 1)``."""
    theta2 = (phi * phi).sum(-1, keepdim=True)
    theta = theta2.sqrt()
    small = theta < 1e-4
    safe = torch.where(small, torch.ones_like(theta), theta)
    big = (1.0 - safe * torch.cos(safe / 2) / (2 * torch.sin(safe / 2))) / (safe * safe)
    return torch.where(small, 1.0 / 12.0 + theta2 / 720.0, big)


def _so3_left_jacobian_inv_apply(phi: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """``Jl^-1(phi) v`` by cross products (no 3x3 matrices). ``(..., 3)`` x2 -> ``(..., 3)``."""
    pv = torch.linalg.cross(phi, v)
    return v - 0.5 * pv + _so3_left_jacobian_inv_coeff(phi) * torch.linalg.cross(phi, pv)


def _jacobian_inv_coeffs(theta2: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``alpha``, ``beta`` in ``Jr^-1(xi) = I + ad/2 + alpha ad^2 + beta ad^4`` from ``theta^2 = |phi|^2``.

    ``Jr^-1(xi) = f(-ad(xi))`` with ``f(x) = x / (e^x - 1)``. The eigenvalues of ``ad`` are 0
    and ``+-i theta``, each at most a double root of its minimal polynomial, so ``f(-ad)`` equals
    the polynomial that matches ``f`` and ``f'`` there (Hermite interpolation): with
    ``h = theta/2``, ``B = 1 - h cot h`` and ``A = 1/(8 sin^2 h) - cot(h)/(4 theta)``,
    ``alpha = 2B/theta^2 - A`` and ``beta = (B - A theta^2)/theta^4``. Below ``theta = 0.05``
    their Taylor series replace them (the closed form for beta cancels there).
    """
    theta = theta2.sqrt()
    small = theta < 0.05
    s = torch.where(small, torch.ones_like(theta), theta)
    h = s / 2
    sin_h = torch.sin(h)
    cot_h = torch.cos(h) / sin_h
    A = 1 / (8 * sin_h * sin_h) - cot_h / (4 * s)
    B = 1 - h * cot_h
    s2 = s * s
    theta4 = theta2 * theta2
    alpha = torch.where(small, 1 / 12 - theta4 / 30240, 2 * B / s2 - A)
    beta = torch.where(small, -1 / 720 - theta2 / 15120 - theta4 / 403200, (B - A * s2) / (s2 * s2))
    return alpha, beta


def right_jacobian_inv(xi: torch.Tensor) -> torch.Tensor:
    """Inverse right Jacobians ``(..., 6, 6)`` of se3 vectors ``(..., 6)`` = [rho, phi].

    ``Log(Exp(xi) . Exp(d)) = xi + Jr^-1(xi) d + O(|d|^2)``. In closed form as a quartic in
    ``ad(xi) = [[phi^, rho^], [0, phi^]]`` (:func:`_jacobian_inv_coeffs`): two 6x6 products,
    fewer tensor ops on small batches than the 3x3 block formula with Barfoot's Q.
    """
    xi = torch.as_tensor(xi)
    rho, phi = xi[..., :3], xi[..., 3:]
    P = skew(phi)
    ad = torch.zeros(xi.shape[:-1] + (6, 6), dtype=xi.dtype, device=xi.device)
    ad[..., :3, :3] = P
    ad[..., 3:, 3:] = P
    ad[..., :3, 3:] = skew(rho)
    ad2 = ad @ ad
    alpha, beta = _jacobian_inv_coeffs((phi * phi).sum(-1)[..., None, None])
    return torch.eye(6, dtype=xi.dtype, device=xi.device) + 0.5 * ad + alpha * ad2 + beta * (ad2 @ ad2)


def between_error(Z: torch.Tensor, Ti: torch.Tensor, Tj: torch.Tensor) -> torch.Tensor:
    """Between-factor errors ``e = Log(Z^-1 . Ti^-1 . Tj)`` ``(..., 6)`` [rho, phi].

    ``Z`` ``(..., 4, 4)`` is the measured ``i_T_j``; ``Ti``, ``Tj`` are ``start_T_i``, ``start_T_j``.
    """
    return log(inverse(Ti @ Z) @ Tj)


def between_jacobians(Z: torch.Tensor, Ti: torch.Tensor, Tj: torch.Tensor, e: torch.Tensor | None = None
                      ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Errors ``(E, 6)`` and their Jacobians ``(E, 6, 6)`` w.r.t. right perturbations of Ti, Tj.

    With ``e = Log(Z^-1 Ti^-1 Tj)``: ``de/d(delta_j) = Jr^-1(e)`` and
    ``de/d(delta_i) = -Jr^-1(e) . Ad(Tj^-1 Ti)``. ``e``: the errors, if already computed
    (:func:`between_error` of the same arguments).
    """
    if e is None:
        e = between_error(Z, Ti, Tj)
    Jr_inv = right_jacobian_inv(e)
    Ji = -Jr_inv @ adjoint(inverse(Tj) @ Ti)
    return e, Ji, Jr_inv


def prior_jacobian(Z: torch.Tensor, Ti: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Prior errors ``e = Log(Z^-1 Ti)`` ``(P, 6)`` and Jacobians ``Jr^-1(e)`` ``(P, 6, 6)``."""
    e = log(inverse(Z) @ Ti)
    return e, right_jacobian_inv(e)


def retract(T: torch.Tensor, delta: torch.Tensor) -> torch.Tensor:
    """Right retraction ``T . Exp(delta)``, ``T (..., 4, 4)``, ``delta (..., 6)`` [rho, phi]."""
    return T @ exp(delta)
