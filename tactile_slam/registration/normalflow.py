"""NormalFlow registration in torch, batched over pairs (method.md section 4).

Usage::

    prep = prepare_reference(keyframe)                 # once per reference
    res = register_prepared(prep, targets, init)        # (B,) results, never raises
    tar_T_ref = normalflow(ref, tar)                     # one pair, raises TrackingLost

``tar_T_ref`` maps a static object point from reference-sensor into target-sensor
coordinates (metres, float64). The Gauss-Newton solve estimates
``(wx, wy, wz, tx, ty)`` in inverse-compositional form over the reference's
highest-|curvature| contact pixels; ``tz`` comes afterwards from the mean height
difference; CCS and SCR score the result. Failed pairs (too few shared samples,
degenerate normal equations, no valid height sample, low or undefined scores) come back
with ``ok = False`` and a finite pose.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F

from tactile_slam.config import NormalFlowConfig
from tactile_slam.geometry.frame import Frame
from tactile_slam.registration.jacobian import euler_to_matrix, jacobian_analytic, jacobian_autograd, sobel_at
from tactile_slam.registration.result import RegistrationError, RegistrationResult, TrackingLost
from tactile_slam.registration.sampling import select_samples

JACOBIANS = {"analytic": jacobian_analytic, "autograd": jacobian_autograd}


@dataclass
class Level:
    """One Gauss-Newton level of a prepared reference.

    Attributes:
        normals_t: ``(B, 3, K)`` reference normals n_k at this level, channels first.
        jacobian: ``(B, 3K, 5)`` float64 rows of J_k, channel-major (all x rows, then
            all y rows, then all z rows), matching ``(B, 3, K)`` residuals.
        jtj: ``(B, K, 25)`` float64 per-sample ``J_k^T J_k``.
        factor: 1 for full resolution; ``f > 1`` for maps averaged over ``f x f``
            blocks (a coarse level: wider basin, used to initialise the next level).
    """

    normals_t: torch.Tensor
    jacobian: torch.Tensor
    jtj: torch.Tensor
    factor: int


@dataclass
class PreparedReference:
    """Per-reference quantities, computed once and reused for every target.

    Attributes:
        points: ``(B, K, 3)`` sample points P_k, metres, reference sensor frame.
        curvature: ``(B, K)`` reference curvature L_ref,k (1/px).
        valid: ``(B, K)`` bool, False for padding.
        levels: coarse to fine; the last is full resolution.
        shape: ``(H, W)`` of the image.
        m_per_px: metres per pixel.
    """

    points: torch.Tensor
    curvature: torch.Tensor
    valid: torch.Tensor
    levels: list[Level]
    shape: tuple[int, int]
    m_per_px: float

    def __len__(self) -> int:
        return self.points.shape[0]

    @property
    def dtype(self) -> torch.dtype:
        return self.points.dtype

    @property
    def device(self) -> torch.device:
        return self.points.device


def _check_finite(frame: Frame, what: str) -> None:
    total = frame.normals.sum() + frame.height.sum() + frame.curvature.sum()
    if not bool(torch.isfinite(total)):
        raise RegistrationError(f"{what} frame contains NaN or Inf in its normals, height or curvature")


def _check_config(config: NormalFlowConfig, shape: tuple[int, int] | None = None) -> None:
    if config.jacobian not in JACOBIANS:
        raise RegistrationError(f"normalflow.jacobian must be one of {tuple(JACOBIANS)}, got {config.jacobian!r}")
    if config.max_iters < 1 or config.min_iters < 1 or config.coarse_max_iters < 1:
        raise RegistrationError("normalflow.max_iters, min_iters and coarse_max_iters must be >= 1")
    if config.lm_damping < 0:
        raise RegistrationError(f"normalflow.lm_damping must be >= 0, got {config.lm_damping}")
    for f in config.coarse_factors:
        if f < 2 or (shape is not None and (shape[0] % f or shape[1] % f)):
            raise RegistrationError(f"normalflow.coarse_factors must be >= 2 and divide the image size, got {f}")


def metric_points(height: torch.Tensor, idx: torch.Tensor, m_per_px: float) -> torch.Tensor:
    """Metric points of pixels (method.md section 1.2).

    Args:
        height: ``(B, H, W)`` px.
        idx: ``(B, K)`` row-major pixel indices.

    Returns:
        ``(B, K, 3)`` metres: ``((c - (W-1)/2) s, (r - (H-1)/2) s, h s)``.
    """
    b, h, w = height.shape
    r = (idx // w).to(height.dtype)
    c = (idx % w).to(height.dtype)
    z = height.reshape(b, -1).gather(1, idx)
    return torch.stack([c - (w - 1) / 2.0, r - (h - 1) / 2.0, z], dim=-1) * m_per_px


def _level(points, normals, dn, valid, factor, jacobian) -> Level:
    """Jacobian rows and per-sample ``J^T J`` for normals ``(B, K, 3)`` and their
    derivatives per metre ``(B, K, 3, 2)``."""
    b = points.shape[0]
    jac = JACOBIANS[jacobian](points.double(), normals.double(), dn.double())
    jac = jac * valid[..., None, None]  # (B, K, 3, 5)
    jtj = torch.einsum("bkci,bkcj->bkij", jac, jac).reshape(b, -1, 25)
    rows = jac.transpose(1, 2).reshape(b, -1, 5)
    return Level(normals.transpose(1, 2).contiguous(), rows, jtj, factor)


def _coarse_level(normals_map, points, valid, s, factor, jacobian) -> Level:
    """A level on ``factor x factor`` block averages of the normal map. Values and
    5x5 Sobel derivatives of the averaged map are sampled bilinearly at the samples."""
    b, h, w, _ = normals_map.shape
    pooled = F.avg_pool2d(normals_map.permute(0, 3, 1, 2), factor)  # (B, 3, h/f, w/f)
    smooth = torch.tensor([1.0, 4.0, 6.0, 4.0, 1.0], dtype=pooled.dtype, device=pooled.device)
    deriv = torch.tensor([-1.0, -2.0, 0.0, 2.0, 1.0], dtype=pooled.dtype, device=pooled.device)
    kernels = torch.stack([torch.outer(smooth, deriv), torch.outer(deriv, smooth)])[:, None] / 128.0
    padded = F.pad(pooled.reshape(b * 3, 1, *pooled.shape[2:]), (2, 2, 2, 2), mode="reflect")
    sob = F.conv2d(padded, kernels).reshape(b, 6, *pooled.shape[2:])  # (x-deriv, y-deriv) per channel
    grid = points[..., :2] * _grid_scale((h, w), s, points, align_corners=False)
    normals = _sample(pooled, grid, "bilinear", False).transpose(1, 2)
    dn = _sample(sob, grid, "bilinear", False).transpose(1, 2).reshape(b, -1, 3, 2) / (factor * s)
    vf = valid.to(normals.dtype)[..., None]
    return _level(points, normals * vf, dn * vf[..., None], valid, factor, jacobian)


def prepare_reference(ref: Frame, config: NormalFlowConfig | None = None, dtype: torch.dtype | None = None
                      ) -> PreparedReference:
    """Select samples and precompute P_k, n_k, L_k and J_k for ``B`` references.

    Args:
        ref: reference frames (``B`` >= 1).
        config: NormalFlow settings (defaults if ``None``).
        dtype: working dtype of the maps (default: the frame's, float32).

    Returns:
        a :class:`PreparedReference` on the frame's device.
    """
    config = config or NormalFlowConfig()
    _check_config(config, ref.shape)
    if len(ref) == 0:
        raise RegistrationError("empty reference batch")
    _check_finite(ref, "reference")
    dtype = dtype or ref.normals.dtype
    b, h, w = ref.height.shape
    s = ref.mm_per_px / 1000.0
    gen = torch.Generator().manual_seed(config.seed) if config.selection == "random" else None
    idx, valid = select_samples(ref.curvature, ref.contact, config.n_samples, config.selection, gen)
    normals_map = ref.normals.to(dtype)
    vf = valid.to(dtype)
    points = metric_points(ref.height.to(dtype), idx, s) * vf[..., None]
    normals = normals_map.reshape(b, -1, 3).gather(1, idx[..., None].expand(-1, -1, 3)) * vf[..., None]
    curv = ref.curvature.to(dtype).reshape(b, -1).gather(1, idx) * vf
    levels = [_coarse_level(normals_map, points, valid, s, f, config.jacobian)
              for f in sorted(config.coarse_factors, reverse=True)]
    levels.append(_level(points, normals, sobel_at(normals_map, idx) / s, valid, 1, config.jacobian))
    return PreparedReference(points, curv, valid, levels, (h, w), s)


def _as_batch(x: torch.Tensor, b: int) -> torch.Tensor:
    return x.expand(b, *x.shape[1:]) if x.shape[0] == 1 and b > 1 else x


def _grid_scale(shape: tuple[int, int], s: float, like: torch.Tensor, align_corners: bool = True) -> torch.Tensor:
    """Factor taking metric ``(x, y)`` (origin at the image centre) to grid_sample
    coordinates. ``(2,)``."""
    h, w = shape
    if align_corners:  # pixel centres 0 and W-1 at -1 and 1
        return torch.tensor([2.0 / (s * (w - 1)), 2.0 / (s * (h - 1))], dtype=like.dtype, device=like.device)
    return torch.tensor([2.0 / (s * w), 2.0 / (s * h)], dtype=like.dtype, device=like.device)  # image edges


def _sample(maps: torch.Tensor, grid: torch.Tensor, mode: str, align_corners: bool = True) -> torch.Tensor:
    """``(B, C, H, W)`` maps at ``(B, K, 2)`` grid points, zero outside -> ``(B, C, K)``."""
    out = F.grid_sample(maps, grid.unsqueeze(1), mode=mode, padding_mode="zeros", align_corners=align_corners)
    return out.view(maps.shape[0], maps.shape[1], grid.shape[1])


def _inside(grid: torch.Tensor) -> torch.Tensor:
    """``0 <= x' and 0 <= y'``. The upper bounds ``x' < W``, ``y' < H`` need no test:
    nearest sampling past ``W - 0.5`` and bilinear past ``W - 1`` weigh in the zero
    padding, so a contact value above 0.5 already implies them. ``(B, K, 2)`` -> ``(B, K)``."""
    return grid.amin(-1) >= -1.0


def _solve(ata: torch.Tensor, atb: torch.Tensor, ridge: torch.Tensor, damping: float
           ) -> tuple[torch.Tensor, torch.Tensor]:
    """Damped 5x5 normal equations ``(A + ridge + damping diag(A)) x = b`` by Cholesky
    (Marquardt scaling; the tiny ``ridge`` keeps unobservable directions at 0 instead of
    NaN). Returns ``(delta (B, 5), solved (B,) bool)``."""
    damped = ata + ridge
    if damping > 0:
        damped = damped + torch.diag_embed(damping * ata.diagonal(dim1=1, dim2=2))
    chol, info = torch.linalg.cholesky_ex(damped)
    return torch.cholesky_solve(atb.unsqueeze(-1), chol).squeeze(-1), info == 0


@dataclass
class _State:
    """Gauss-Newton state of ``B`` pairs: ``tar_T_ref = [rot | (txy, 0)]`` (float64)."""

    rot: torch.Tensor  # (B, 3, 3)
    txy: torch.Tensor  # (B, 2)
    active: torch.Tensor  # (B,) still iterating
    lost: torch.Tensor  # (B,) too few shared samples or an unsolvable step
    converged: torch.Tensor  # (B,)
    iterations: torch.Tensor  # (B,) int64
    ata: torch.Tensor  # (B, 5, 5) last normal equations


def _gauss_newton(st: _State, lvl: Level, points, valid, n_map, c_map, scale, align_corners, config,
                  max_iters: int, min_iters: int, tol_scale: float) -> _State:
    """Inverse-compositional Gauss-Newton iterations of one level (method.md 4.4)."""
    b, k = valid.shape
    dt = points.dtype
    jtj, jac = _as_batch(lvl.jtj, b), _as_batch(lvl.jacobian, b)
    normals_t = _as_batch(lvl.normals_t, b)
    ridge = torch.diag_embed(1e-12 * jtj.sum(1).view(b, 5, 5).diagonal(dim1=1, dim2=2).amax(1, keepdim=True)
                             .expand(b, 5))
    # squared step norms (rotation, translation) against squared tolerances in one product
    split = torch.tensor([[1.0, 0.0]] * 3 + [[0.0, 1.0]] * 2, dtype=torch.float64, device=points.device)
    tol2 = torch.tensor([config.rot_tol, config.trans_tol_m], dtype=torch.float64, device=points.device) ** 2
    tol2 = tol2 * tol_scale**2
    rot, txy, active, lost, converged = st.rot, st.txy, st.active.clone(), st.lost.clone(), st.converged.clone()
    iterations, ata = st.iterations.clone(), st.ata
    for i in range(max_iters):
        r_dt = rot.to(dt)
        grid = torch.baddbmm((txy.to(dt) * scale).unsqueeze(1), points, (r_dt[:, :2] * scale[:, None]).transpose(1, 2))
        near = _sample(c_map, grid, "nearest", align_corners).view(b, k)
        shared = (near > 0.5) & _inside(grid) & valid
        # residual R^T N_tar(x') - n, (B, 3, K), and the normal equations in float64
        res = torch.bmm(r_dt.transpose(1, 2), _sample(n_map, grid, "bilinear", align_corners)) - normals_t
        w = shared.to(torch.float64)
        ata = torch.bmm(w.unsqueeze(1), jtj).view(b, 5, 5)
        atb = torch.bmm((res.to(torch.float64) * w.unsqueeze(1)).view(b, 1, 3 * k), jac).view(b, 5)
        delta, solved = _solve(ata, atb, ridge, config.lm_damping)
        # too few shared samples, or an unsolvable step: lost (the pose stays as it was)
        solved &= torch.isfinite(delta).all(1)
        bad = active & ((shared.sum(1) < config.min_shared) | ~solved)
        lost |= bad
        active &= ~bad
        delta = torch.where(active[:, None], delta, torch.zeros_like(delta))
        # T <- T dT^-1 with dT = [R(w) | (tx, ty, 0)]; tz stays 0 during the iterations
        rot = rot @ euler_to_matrix(delta[:, :3]).transpose(1, 2)
        txy = txy - (rot[:, :2, :2] @ delta[:, 3:, None]).squeeze(-1)
        iterations += active
        if i + 1 >= min_iters:
            step = ((delta.square() @ split) < tol2).all(1)
            converged |= active & step
            active &= ~step
            if not bool(active.any()):
                break
    return _State(rot, txy, active, lost, converged, iterations, ata)


def register_prepared(
    prep: PreparedReference,
    tar: Frame,
    init_tar_T_ref: torch.Tensor | None = None,
    config: NormalFlowConfig | None = None,
) -> RegistrationResult:
    """Register ``B`` targets to prepared references (one reference, broadcast, or ``B``).

    Args:
        prep: from :func:`prepare_reference`, batch 1 or ``B``.
        tar: ``B`` target frames of the same size and scale.
        init_tar_T_ref: ``(B, 4, 4)`` or ``(4, 4)`` initial tar_T_ref (metres; its tz
            is ignored), identity if ``None``.
        config: NormalFlow settings; must match the one used for ``prep``.

    Returns:
        a :class:`RegistrationResult` of ``B`` pairs; failures are reported, not raised.
    """
    config = config or NormalFlowConfig()
    _check_config(config, prep.shape)
    b = len(tar)
    if b == 0:
        raise RegistrationError("empty target batch")
    if len(prep) not in (1, b):
        raise RegistrationError(f"{len(prep)} references cannot be paired with {b} targets")
    if tuple(tar.shape) != tuple(prep.shape):
        raise RegistrationError(f"target size {tuple(tar.shape)} differs from reference size {prep.shape}")
    if abs(tar.mm_per_px / 1000.0 - prep.m_per_px) > 1e-12:
        raise RegistrationError(f"target scale {tar.mm_per_px} mm/px differs from the reference's")
    _check_finite(tar, "target")
    dev, dt = prep.device, prep.dtype
    if init_tar_T_ref is None:
        init_tar_T_ref = torch.eye(4, dtype=torch.float64, device=dev)
    init = torch.as_tensor(init_tar_T_ref, dtype=torch.float64, device=dev)
    if init.ndim == 2:
        init = init.unsqueeze(0)
    if init.shape[1:] != (4, 4) or init.shape[0] not in (1, b):
        raise RegistrationError(f"init_tar_T_ref must be (B, 4, 4) or (4, 4), got {tuple(init_tar_T_ref.shape)}")
    if not bool(torch.isfinite(init).all()):
        raise RegistrationError("init_tar_T_ref contains NaN or Inf")

    points, valid = _as_batch(prep.points, b), _as_batch(prep.valid, b)
    n_map = tar.normals.to(device=dev, dtype=dt).permute(0, 3, 1, 2)  # a view: no copy
    c_map = tar.contact.to(device=dev, dtype=dt).unsqueeze(1)
    flags = torch.zeros(b, dtype=torch.bool, device=dev)
    st = _State(init[:, :3, :3].expand(b, 3, 3), init[:, :2, 3].expand(b, 2), ~flags, flags, flags,
                torch.zeros(b, dtype=torch.int64, device=dev), torch.zeros((b, 5, 5), dtype=torch.float64, device=dev))
    for lvl in prep.levels[:-1]:  # coarse levels: block-averaged target maps
        f = lvl.factor
        scale = _grid_scale(prep.shape, prep.m_per_px, points, align_corners=False)
        st = _gauss_newton(st, lvl, points, valid, F.avg_pool2d(n_map, f), F.avg_pool2d(c_map, f), scale, False,
                           config, config.coarse_max_iters, 1, float(f))
        st.active, st.converged = ~st.lost, torch.zeros_like(st.lost)
    scale = _grid_scale(prep.shape, prep.m_per_px, points)
    st = _gauss_newton(st, prep.levels[-1], points, valid, n_map, c_map, scale, True, config,
                       config.max_iters, config.min_iters, 1.0)
    T = torch.eye(4, dtype=torch.float64, device=dev).repeat(b, 1, 1)
    T[:, :3, :3] = st.rot
    T[:, :2, 3] = st.txy
    h_map = tar.height.to(device=dev, dtype=dt).unsqueeze(1)
    maps = (h_map, tar.curvature.to(device=dev, dtype=dt).unsqueeze(1), c_map)
    return _finish(prep, points, valid, maps, T, st, config, scale)


def _finish(prep, points, valid, maps, T, st, config, scale):
    """tz from the height difference, CCS/SCR, degeneracy, and the ok flag."""
    b, k = valid.shape
    dt = points.dtype
    h_map, l_map, c_map = maps
    moved = torch.baddbmm(T[:, :3, 3].to(dt).unsqueeze(1), points, T[:, :3, :3].to(dt).transpose(1, 2))
    grid = moved[..., :2] * scale
    inside = _inside(grid) & valid
    # tz: mean of s*H_tar - (R P)_z over samples landing in the target contact (nearest)
    vz = ((_sample(c_map, grid, "nearest").view(b, k) > 0.5) & inside).double()
    n_z = vz.sum(1)
    h_tar = _sample(h_map, grid, "bilinear").view(b, k).double()
    dz = (h_tar * prep.m_per_px - moved[..., 2].double()) * vz
    tz_ok = n_z > 0
    T[:, 2, 3] = torch.where(tz_ok, dz.sum(1) / n_z.clamp_min(1.0), torch.zeros_like(n_z))
    # CCS and SCR over the samples landing in the target contact (bilinear)
    sh = (_sample(c_map, grid, "bilinear").view(b, k) > 0.5) & inside
    shf = sh.double()
    l_tar = _sample(l_map, grid, "bilinear").view(b, k).double()
    l_ref = _as_batch(prep.curvature, b).double()
    scr = (l_ref.abs() * shf).sum(1) / l_ref.abs().sum(1)
    ccs = (l_ref * l_tar * shf).sum(1) / torch.sqrt((l_ref.square() * shf).sum(1) * (l_tar.square() * shf).sum(1))
    # degenerate: eigenvalue ratio of the normal equations, translations scaled by the
    # samples' RMS spread so that both parts measure displacement
    xy = points[..., :2].double()
    vf = valid.double()[..., None]
    centre = (xy * vf).sum(1, keepdim=True) / vf.sum(1, keepdim=True).clamp_min(1.0)
    spread = ((xy - centre).square() * vf).sum((1, 2)) / vf.sum((1, 2)).clamp_min(1.0)
    ones = torch.ones((b, 3), dtype=torch.float64, device=T.device)
    sc = torch.cat([ones, spread.sqrt()[:, None].expand(b, 2)], dim=1)
    eig = torch.linalg.eigvalsh(st.ata * sc[:, :, None] * sc[:, None, :])
    degenerate = ~(eig[:, 0] > config.degenerate_eig * eig[:, -1])
    ok = ~st.lost & tz_ok & ~degenerate
    if config.check_scores:
        ok &= (ccs >= config.ccs_threshold) & (scr >= config.scr_threshold)
    return RegistrationResult(tar_T_ref=T, ccs=ccs, scr=scr, n_shared=sh.sum(1), iterations=st.iterations,
                              converged=st.converged, ok=ok)


def register(
    ref: Frame,
    tar: Frame,
    init_tar_T_ref: torch.Tensor | None = None,
    config: NormalFlowConfig | None = None,
    dtype: torch.dtype | None = None,
) -> RegistrationResult:
    """Register ``B`` pairs ``(ref[i], tar[i])`` (or one reference to ``B`` targets).

    Args:
        ref: ``B`` (or 1) reference frames.
        tar: ``B`` target frames.
        init_tar_T_ref: ``(B, 4, 4)``/``(4, 4)`` float64 initial tar_T_ref, metres, or
            ``None`` for identity.
        config: NormalFlow settings.
        dtype: working dtype (default: the frames', float32).

    Returns:
        ``B`` results; failed pairs have ``ok = False``.
    """
    return register_prepared(prepare_reference(ref, config, dtype), tar, init_tar_T_ref, config)


def register_pair(
    ref: Frame,
    tar: Frame,
    init_tar_T_ref: torch.Tensor | None = None,
    config: NormalFlowConfig | None = None,
) -> RegistrationResult:
    """Register one pair (``B = 1`` frames); returns a result of length 1."""
    if len(ref) != 1 or len(tar) != 1:
        raise RegistrationError(f"register_pair takes single frames, got batches of {len(ref)} and {len(tar)}")
    return register(ref, tar, init_tar_T_ref, config)


def normalflow(
    ref: Frame,
    tar: Frame,
    init_tar_T_ref: torch.Tensor | None = None,
    config: NormalFlowConfig | None = None,
) -> torch.Tensor:
    """One pair: ``(4, 4)`` float64 tar_T_ref (metres), or raise :class:`TrackingLost`."""
    res = register_pair(ref, tar, init_tar_T_ref, config)
    if not bool(res.ok[0]):
        raise TrackingLost(res)
    return res.tar_T_ref[0]
