"""NormalFlow registration in torch, batched over pairs (method.md section 4).

Usage::

    prep = prepare_reference(keyframe)                 # once per reference
    res = register_prepared(prep, targets, init)        # (B,) results, never raises
    tar_T_ref = normalflow(ref, tar)                     # one pair, raises TrackingLost
    wide = NormalFlowConfig(fallback_factors=(16, 4))    # failures retried coarse to fine:
    tar_T_ref = normalflow(ref, tar, None, wide)         # for a poor (or no) initial guess

``tar_T_ref`` maps a static object point from reference-sensor into target-sensor
coordinates (metres, float64). The Gauss-Newton solve estimates
``(wx, wy, wz, tx, ty)`` in inverse-compositional form over reference contact pixels of
high |curvature|, spread over the contact (``NormalFlowConfig.selection``); ``tz`` comes
afterwards from the mean height difference; CCS and SCR score the result. Failed pairs
(too few shared samples, degenerate normal equations, no valid height sample, low or
undefined scores) come back with ``ok = False`` and a finite pose.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields

import numpy as np
import torch
import torch.nn.functional as F
from scipy.linalg.lapack import dposv

from tactile_slam.config import JACOBIAN_KINDS, ConfigError, NormalFlowConfig, lower_limit
from tactile_slam.geometry.frame import CroppedFrame, Frame, WindowBatch
from tactile_slam.geometry.morphology import as_weights
from tactile_slam.registration.jacobian import euler_to_matrix, jacobian_analytic, jacobian_autograd, sobel_at
from tactile_slam.registration.result import RegistrationError, RegistrationResult, TrackingLost
from tactile_slam.registration.sampling import nonzero_2d, select_samples, within_slope
from tactile_slam.registration.shift import correlation_shift

JACOBIANS = dict(zip(JACOBIAN_KINDS, (jacobian_analytic, jacobian_autograd)))


@dataclass
class Level:
    """One Gauss-Newton level of a prepared reference.

    Attributes:
        normals_t: ``(B, 3, K)`` reference normals n_k at this level, channels first.
        jacobian_t: ``(B, 5, 3K)`` J^T in the working dtype, columns channel-major (all
            x rows of J, then all y rows, then all z rows), matching flattened
            ``(B, 3, K)`` residuals; zero for padding.
        jtj: ``(B, K, 25)`` float64 per-sample ``J_k^T J_k`` (zero for padding).
        ata_full: ``(B, 5, 5)`` float64 ``sum_k J_k^T J_k``; an iteration subtracts the
            samples it does not share.
        factor: 1 for full resolution; ``f > 1`` for maps averaged over ``f x f``
            blocks (a coarse level: wider basin, used to initialise the next level).
    """

    normals_t: torch.Tensor
    jacobian_t: torch.Tensor
    jtj: torch.Tensor
    ata_full: torch.Tensor
    factor: int


@dataclass
class PreparedReference:
    """Per-reference quantities, computed once and reused for every target.

    Attributes:
        points_t: ``(B, 3, K)`` sample points P_k, metres, reference sensor frame,
            channels first (the layout the warp's product wants); :attr:`points` is the
            ``(B, K, 3)`` view.
        curvature: ``(B, K)`` reference curvature L_ref,k (1/px).
        spread: ``(B,)`` float64 RMS distance of the samples from their centroid (m),
            scaling translations in the degeneracy test.
        valid: ``(B, K)`` bool, False for padding.
        levels: coarse to fine; the last is full resolution.
        shape: ``(H, W)`` of the image.
        m_per_px: metres per pixel.
        normals_map: ``(B, H, W, 3)`` the references' normal maps in the working dtype
            (the source of coarse levels built later, :meth:`retry_levels`).
        contact: ``(B, H, W)`` bool contact masks (the fallback's shift search).
        settings: :func:`reference_settings` of the configuration it was prepared with
            (another solve may reuse it when its own settings are equal).

    :func:`prepare_reference` builds it under ``torch.inference_mode``: its tensors are
    read-only inputs of later registrations (an in-place change outside inference
    mode raises).
    """

    points_t: torch.Tensor
    curvature: torch.Tensor
    spread: torch.Tensor
    valid: torch.Tensor
    levels: list[Level]
    shape: tuple[int, int]
    m_per_px: float
    normals_map: torch.Tensor
    contact: torch.Tensor
    settings: tuple = ()

    def __len__(self) -> int:
        return self.points_t.shape[0]

    @property
    def points(self) -> torch.Tensor:
        """``(B, K, 3)`` view of :attr:`points_t`."""
        return self.points_t.mT

    @property
    def dtype(self) -> torch.dtype:
        return self.points_t.dtype

    def __getitem__(self, i: slice | torch.Tensor) -> "PreparedReference":
        """The references ``i`` (a slice or an index tensor), all of their levels."""
        levels = [Level(lvl.normals_t[i], lvl.jacobian_t[i], lvl.jtj[i], lvl.ata_full[i], lvl.factor)
                  for lvl in self.levels]
        return PreparedReference(self.points_t[i], self.curvature[i], self.spread[i], self.valid[i], levels,
                                 self.shape, self.m_per_px, self.normals_map[i], self.contact[i], self.settings)

    def retry_levels(self, ids: np.ndarray | None, factors: tuple[int, ...], jacobian: str) -> "PreparedReference":
        """The references ``ids`` (all if ``None``) with coarse levels ``factors`` in
        front of the full-resolution level: the pyramid of the fallback solve."""
        sub = self if ids is None else self[torch.from_numpy(ids).to(self.device)]
        levels = [_coarse_level(sub.normals_map, sub.points, sub.valid, self.m_per_px, f, jacobian)
                  for f in sorted(factors, reverse=True)]
        prep = PreparedReference(sub.points_t, sub.curvature, sub.spread, sub.valid, [*levels, sub.levels[-1]],
                                 self.shape, self.m_per_px, sub.normals_map, sub.contact,
                                 (*self.settings[:-2], jacobian, tuple(sorted(factors, reverse=True))) if self.settings
                                 else ())
        _check_reference_finite(prep)  # the coarse levels read the normal map around the samples
        return prep

    @property
    def device(self) -> torch.device:
        return self.points_t.device


def _check_reference_finite(prep: "PreparedReference") -> None:
    """NaN or Inf in what the reference contributes (sample points, normals, curvature,
    the normal map's derivatives behind every level's Jacobian) is an input error. Only
    the values read are checked: a scan of the full maps would cost several times its
    own time in evicted cache on the CPU."""
    total = prep.points_t.sum() + prep.curvature.sum()
    for lvl in prep.levels:
        total = total + lvl.normals_t.sum() + lvl.jacobian_t.sum()
    if not bool(torch.isfinite(total)):
        raise RegistrationError("reference frame contains NaN or Inf in its normals, height or curvature "
                                "at the samples")


def _target_error(what: str) -> RegistrationError:
    return RegistrationError(f"target frame contains NaN or Inf in its {what} where the samples land")


def _check_config(config: NormalFlowConfig, shape: tuple[int, int] | None = None) -> None:
    """:meth:`NormalFlowConfig.check`, raised as a :class:`RegistrationError`."""
    if not isinstance(config, NormalFlowConfig):
        raise RegistrationError(f"expected a NormalFlowConfig (e.g. config.normalflow), got {type(config).__name__}")
    try:
        config.check(shape)
    except ConfigError as exc:
        raise RegistrationError(str(exc)) from None


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


def _level(points_t, normals_t, dn_t, valid, factor, jacobian) -> Level:
    """Jacobian rows and normal matrices for points and normals ``(B, 3, K)`` and the
    normals' derivatives per metre ``(B, 3, 2, K)``, in the dtype of ``points_t``.
    The normal matrices are float64 products of that Jacobian, the values the
    right-hand sides use."""
    b, k = valid.shape
    jac = JACOBIANS[jacobian](points_t, normals_t, dn_t)  # (B, 5, 3, K)
    jac_t = (jac * as_weights(valid, jac.dtype)[:, None, None]).reshape(b, 5, 3 * k)  # columns channel-major
    j64 = jac_t.double()
    return Level(normals_t.contiguous(), jac_t, _outer_products(j64.view(b, 5, 3, k)), torch.bmm(j64, j64.mT), factor)


def _outer_products(jac: torch.Tensor, chunk_samples: int = 8192) -> torch.Tensor:
    """Per-sample ``J_k^T J_k`` of a channels-first Jacobian: ``(B, 5, 3, K)`` ->
    ``(B, K, 25)``. Elementwise over the contiguous sample axis, accumulated in place
    (several times faster than a batched product of 3x5 matrices). Several references
    are stored transposed (an iteration gathers the rows of a pair's unshared samples), a
    few at a time so the intermediate stays in cache; one reference (read whole by a
    matrix product) keeps the products as computed, returned as a transposed view."""
    b, _, _, k = jac.shape
    if b == 1:
        o = torch.mul(jac[:, :, None, 0], jac[:, None, :, 0])
        o.addcmul_(jac[:, :, None, 1], jac[:, None, :, 1]).addcmul_(jac[:, :, None, 2], jac[:, None, :, 2])
        return o.view(1, 25, k).mT
    out = torch.empty((b, k, 25), dtype=jac.dtype, device=jac.device)
    step = max(1, chunk_samples // max(k, 1))
    for i in range(0, b, step):
        j = jac[i:i + step]
        o = torch.mul(j[:, :, None, 0], j[:, None, :, 0])
        o.addcmul_(j[:, :, None, 1], j[:, None, :, 1]).addcmul_(j[:, :, None, 2], j[:, None, :, 2])
        out[i:i + step] = o.view(-1, 25, k).mT
    return out


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
    grid = points[..., :2] * torch.as_tensor(_grid_scale((h, w), s, False), dtype=points.dtype, device=points.device)
    vf = valid.to(points.dtype)[:, None]
    normals_t = _sample(pooled, grid, "bilinear", False) * vf  # (B, 3, K)
    dn_t = _sample(sob, grid, "bilinear", False).view(b, 3, 2, -1) * (vf[:, None] / (factor * s))
    return _level(points.mT, normals_t, dn_t, valid, factor, jacobian)


def reference_settings(config: NormalFlowConfig) -> tuple:
    """What :func:`prepare_reference` takes from a configuration: the sample selection
    (count, rule, seed, cell size, slope limits), the Jacobian and the
    coarse levels. Two configurations with equal settings prepare a frame identically (the
    thresholds act later)."""
    return (config.n_samples, config.selection, config.seed if config.selection == "random" else None,
            config.sample_cell_px if config.selection == "spread" else None, config.decoded_max_slope,
            config.max_slope, config.jacobian, tuple(sorted(config.coarse_factors, reverse=True)))


@torch.inference_mode()
def prepare_reference(ref: Frame, config: NormalFlowConfig | None = None, dtype: torch.dtype | None = None
                      ) -> PreparedReference:
    """Select samples and precompute P_k, n_k, L_k and J_k for ``B`` references
    (under ``torch.inference_mode``, see :class:`PreparedReference`).

    Args:
        ref: reference frames (``B`` >= 1); a :class:`CroppedFrame` (a compacted
            keyframe's maps) is expanded to full size first.
        config: NormalFlow settings (defaults if ``None``).
        dtype: working dtype of the maps, float32 or float64 (default: the frame's).

    Returns:
        a :class:`PreparedReference` on the frame's device.
    """
    config = config or NormalFlowConfig()
    ref = _full(ref, "reference")
    _check_config(config, ref.shape)
    if len(ref) == 0:
        raise RegistrationError("empty reference batch")
    dtype = _check_dtype(dtype or ref.normals.dtype)
    b, h, w = ref.height.shape
    s = ref.mm_per_px / 1000.0
    gen = torch.Generator().manual_seed(config.seed) if config.selection == "random" else None
    limit = lower_limit(config.max_slope, config.decoded_max_slope, ref.decoded)  # steepest |n_xy| / |n_z|
    region = ref.contact if limit is None else within_slope(ref.normals, ref.contact, limit)
    idx, valid = select_samples(ref.curvature, region, config.n_samples, config.selection, gen,
                                config.sample_cell_px)
    normals_map = ref.normals.to(dtype)
    vf = valid.to(dtype)
    points = metric_points(ref.height.to(dtype), idx, s) * vf[..., None]
    normals = _rows(normals_map, idx) * vf[..., None]
    curv = ref.curvature.to(dtype).reshape(b, -1).gather(1, idx) * vf
    levels = [_coarse_level(normals_map, points, valid, s, f, config.jacobian)
              for f in sorted(config.coarse_factors, reverse=True)]
    dn_t = sobel_at(normals_map, idx).permute(0, 2, 3, 1) / s  # (B, 3, 2, K)
    levels.append(_level(points.mT, normals.mT, dn_t, valid, 1, config.jacobian))
    prep = PreparedReference(points.mT.contiguous(), curv, _spread(points, valid), valid, levels, (h, w), s,
                             normals_map, ref.contact, reference_settings(config))
    _check_reference_finite(prep)
    return prep


def _full(frames, what: str, windows: bool = False) -> Frame | WindowBatch:
    """``frames`` as registration reads them: a :class:`CroppedFrame` expanded to full
    size, a :class:`WindowBatch` where ``windows`` allows it; anything else is a
    :class:`RegistrationError` naming ``what``."""
    if isinstance(frames, CroppedFrame):
        return frames.expand()
    kinds = (Frame, WindowBatch) if windows else (Frame,)
    if not isinstance(frames, kinds):
        names = "Frame, CroppedFrame" + (" or WindowBatch" if windows else "")
        raise RegistrationError(f"{what} must be a {names}, got {type(frames).__name__}")
    return frames


def _check_dtype(dtype: torch.dtype) -> torch.dtype:
    """``dtype`` if NormalFlow can work in it (float32 or float64), else a :class:`RegistrationError`."""
    if dtype not in (torch.float32, torch.float64):
        raise RegistrationError(f"NormalFlow works in float32 or float64, got {dtype}: pass dtype=torch.float32 "
                                "(or build the frames in float32)")
    return dtype


def _spread(points: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    """RMS distance of the valid samples' ``(x, y)`` from their centroid, float64:
    ``sqrt(mean |xy|^2 - |mean xy|^2)`` (padding points are zero).
    ``(B, K, 3)``, ``(B, K)`` -> ``(B,)``."""
    xy = points[..., :2].double()
    n = valid.sum(1, dtype=torch.float64).clamp_min(1.0)[:, None]
    mean_sq = xy.square().sum(1) / n  # (B, 2)
    return (mean_sq - (xy.sum(1) / n).square()).sum(1).clamp_min(0.0).sqrt()


def _rows(maps: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
    """Channel vectors of ``(B, H, W, C)`` maps at ``(B, K)`` row-major pixel indices
    -> ``(B, K, C)`` (one row gather)."""
    b, h, w, c = maps.shape
    flat = idx + torch.arange(b, device=idx.device)[:, None] * (h * w)
    return maps.reshape(b * h * w, c).index_select(0, flat.reshape(-1)).view(b, -1, c)


def _grid_scale(shape: tuple[int, int], s: float, align_corners: bool = True) -> np.ndarray:
    """Factor taking metric ``(x, y)`` (origin at the image centre) to grid_sample
    coordinates of a map of ``shape`` (a window of the image: plus :func:`_grid_offsets`). ``(2,)``."""
    h, w = shape
    if align_corners:  # pixel centres 0 and W-1 at -1 and 1
        return np.array([2.0 / (s * (w - 1)), 2.0 / (s * (h - 1))])
    return np.array([2.0 / (s * w), 2.0 / (s * h)])  # image edges


def _grid_offsets(full: tuple[int, int], window: tuple[int, int], origins: np.ndarray,
                  align_corners: bool = True) -> np.ndarray:
    """Offsets that, added to metric ``(x, y)`` times :func:`_grid_scale` of the ``window``
    size, give grid_sample coordinates in windows of size ``window`` whose first row and
    column in the ``full`` image are ``origins`` ``(b, 2)``: ``(b, 2)`` ``(x, y)``. Zero
    for full-size windows at the origin."""
    (fh, fw), (h, w) = full, window
    size, span = np.array([w, h], dtype=np.float64), np.array([fw - w, fh - h], dtype=np.float64)
    return (span - 2.0 * origins[:, ::-1]) / (size - 1 if align_corners else size)


def window_multiple(config: NormalFlowConfig) -> int:
    """The window alignment (:func:`~tactile_slam.geometry.frame.window_batch`) that
    targets need for every level ``config`` may solve: the lcm of its coarse and
    fallback factors (1 without)."""
    return math.lcm(1, *config.coarse_factors, *config.fallback_factors)


def _sample(maps: torch.Tensor, grid: torch.Tensor, mode: str, align_corners: bool = True) -> torch.Tensor:
    """``(B, C, H, W)`` maps at ``(B, K, 2)`` grid points, zero outside -> ``(B, C, K)``."""
    out = F.grid_sample(maps, grid.unsqueeze(1), mode=mode, padding_mode="zeros", align_corners=align_corners)
    return out.view(maps.shape[0], maps.shape[1], grid.shape[1])


def _inside(grid: torch.Tensor) -> torch.Tensor:
    """``0 <= x' and 0 <= y'``. The upper bounds ``x' < W``, ``y' < H`` need no test:
    nearest sampling past ``W - 0.5`` and bilinear past ``W - 1`` weigh in the zero
    padding, so a contact value above 0.5 already implies them. ``(B, K, 2)`` -> ``(B, K)``."""
    return grid.amin(-1) >= -1.0


def _solve(ata: np.ndarray, atb: np.ndarray, ridge: np.ndarray, damping: float) -> tuple[np.ndarray, np.ndarray]:
    """Damped 5x5 normal equations ``(A + ridge + damping D) x = b`` of all pairs in one
    batched LAPACK call. The tiny ``ridge`` keeps unobservable directions at 0 instead
    of NaN, and makes the matrix positive definite whenever it is finite and not all
    zero. ``D`` (:func:`_damping_diagonal`) is Marquardt's ``diag(A)`` with a floor per
    block, so that damping also bounds the step along an unobservable direction, where
    ``diag(A)`` is 0 and the ridge alone would pass rounding noise through amplified.
    A singular pair makes the batched call raise; then each pair is solved by Cholesky
    (:func:`_solve_each`). ``(b, 5, 5)``, ``(b, 5)`` -> ``(delta (b, 5), solved (b,)
    bool)``; an unsolvable pair gets a zero step and ``solved = False``."""
    damped = ata + ridge
    if damping > 0:
        damped = damped + damping * _damping_diagonal(ata)
    try:
        delta = np.linalg.solve(damped, atb[..., None])[..., 0]
    except np.linalg.LinAlgError:
        return _solve_each(damped, atb)
    solved = np.isfinite(delta).all(1)
    return np.where(solved[:, None], delta, 0.0), solved


def _damping_diagonal(ata: np.ndarray) -> np.ndarray:
    """``diag(A) + 1e-3 diag(m)`` with ``m`` the mean diagonal entry of the rotation block
    for the three rotations and of the translation block for the two translations (each
    in its own unit, so no scale between radians and metres is needed). The floor is
    far below any direction the data constrains, so it slows none of them.
    ``(b, 5, 5)`` -> ``(b, 5, 5)`` diagonal."""
    d = ata.diagonal(axis1=1, axis2=2)
    floor = np.repeat(np.stack([d[:, :3].mean(1), d[:, 3:].mean(1)], 1), [3, 2], axis=1)
    return (d + 1e-3 * floor)[:, :, None] * np.eye(5)


def _solve_each(damped: np.ndarray, atb: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """:func:`_solve` pair by pair by Cholesky (LAPACK ``dposv``), for a batch holding a
    singular pair (a flat contact's all-zero normal equations). ``(b, 5, 5)``, ``(b, 5)``
    -> ``(delta (b, 5), solved (b,) bool)``."""
    delta = np.zeros_like(atb)
    solved = np.zeros(len(atb), dtype=bool)
    for i in range(len(atb)):
        x, info = dposv(damped[i], atb[i])[1:]
        if info == 0 and np.isfinite(x).all():
            delta[i], solved[i] = x, True
    return delta, solved


@dataclass
class _State:
    """Gauss-Newton state of ``B`` pairs, host float64: ``tar_T_ref = [rot | (txy, 0)]``."""

    rot: np.ndarray  # (B, 3, 3)
    txy: np.ndarray  # (B, 2)
    active: np.ndarray  # (B,) still iterating
    lost: np.ndarray  # (B,) too few shared samples or an unsolvable step
    converged: np.ndarray  # (B,)
    iterations: np.ndarray  # (B,) int64
    ata: np.ndarray  # (B, 5, 5) last normal equations
    stalled: np.ndarray  # (B,) stopped by the stall check: failing scores that cannot pass in time
    checked: np.ndarray  # (B, 2) CCS and SCR at the last stall check (NaN before the first)

    def take(self, ids: np.ndarray) -> "_State":
        return _State(*(getattr(self, f.name)[ids] for f in fields(self)))

    def put(self, ids: np.ndarray, part: "_State") -> None:
        for f in fields(self):
            getattr(self, f.name)[ids] = getattr(part, f.name)


@dataclass
class _Pairs:
    """What an iteration reads for the pairs it works on. Reference tensors keep batch 1
    when one reference is broadcast to every target."""

    points_t: torch.Tensor  # (b or 1, 3, K)
    valid: torch.Tensor  # (b or 1, K)
    normals_t: torch.Tensor  # (b or 1, 3, K)
    jacobian_t: torch.Tensor  # (b or 1, 5, 3K)
    jtj: torch.Tensor  # (b or 1, K, 25) float64
    ata_full: torch.Tensor  # (b or 1, 5, 5) float64
    n_map: torch.Tensor  # (b, 3, h, w) target maps (windows of the full image)
    c_map: torch.Tensor  # (b, 1, h, w)
    offset: np.ndarray  # (b, 2) host float64 grid offsets of the targets' windows (_grid_offsets)
    curvature: torch.Tensor | None = None  # (b or 1, K) reference L at the samples (stall check)
    l_map: torch.Tensor | None = None  # (b, 1, h, w) target curvature (stall check)

    def take(self, ids: np.ndarray) -> "_Pairs":
        """The pairs ``ids`` (references of batch 1 stay shared)."""
        b = self.n_map.shape[0]
        idx = torch.from_numpy(ids).to(self.n_map.device)

        def pick(x):
            if x is None or (isinstance(x, torch.Tensor) and x.shape[0] == 1 and b > 1):
                return x
            return x[ids] if isinstance(x, np.ndarray) else x[idx]

        return _Pairs(*(pick(getattr(self, f.name)) for f in fields(self)))


def _bmv(m: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """Matrices times vectors: ``(b or 1, M, N)`` and ``(b, N)`` -> ``(b, M)`` (a batched
    matrix-vector product is several times slower than multiply-and-sum on the CPU)."""
    return (m[0] @ x.T).T if m.shape[0] == 1 else (m * x.unsqueeze(1)).sum(-1)


def _shared_normal_matrix(pairs: _Pairs, shared: torch.Tensor) -> torch.Tensor:
    """``sum_k J_k^T J_k`` over the shared samples, in float64. ``(b, K)`` -> ``(b, 5, 5)``.

    One reference: a single ``(b, K) x (K, 25)`` product. One reference per pair:
    the full matrices minus the valid samples that are not shared (usually few), so
    that no pair re-reads all of its ``J^T J``."""
    b, k = shared.shape
    if pairs.jtj.shape[0] == 1:
        return (shared.double() @ pairs.jtj[0]).view(b, 5, 5)
    pair, sample = nonzero_2d(pairs.valid & ~shared)
    part = torch.zeros((b, 25), dtype=torch.float64, device=shared.device)
    part.index_add_(0, pair, pairs.jtj.view(-1, 25).index_select(0, sample + pair * k))
    return pairs.ata_full - part.view(b, 5, 5)


def _grid(pairs: _Pairs, motion: torch.Tensor) -> torch.Tensor:
    """Grid coordinates of the samples under the packed poses: ``(b, 5, 4)`` -> ``(b, K, 2)``."""
    return torch.baddbmm(motion[:, :2, 3:], motion[:, :2, :3], pairs.points_t.expand(len(motion), -1, -1)).mT


def _scores(l_ref: np.ndarray, l_tar: np.ndarray, shared: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """CCS and SCR (method.md 4.5) over the ``shared`` samples, host float64; undefined
    scores are NaN. ``(b or 1, K)``, ``(b, K)``, ``(b, K)`` bool -> ``(ccs (b,), scr (b,))``."""
    with np.errstate(divide="ignore", invalid="ignore"):
        scr = (np.abs(l_ref) * shared).sum(1) / np.abs(l_ref).sum(1)
        ccs = (l_ref * l_tar * shared).sum(1) / np.sqrt((l_ref ** 2 * shared).sum(1) * (l_tar ** 2 * shared).sum(1))
    return ccs, scr


def _passes(ccs: np.ndarray, scr: np.ndarray, config: NormalFlowConfig) -> np.ndarray:
    """The score test of ``config`` (NaN fails). ``(b,)`` -> ``(b,)`` bool."""
    return (ccs >= config.ccs_threshold) & (scr >= config.scr_threshold)


def _stall_check(cur: _State, pairs: _Pairs, motion: torch.Tensor, config: NormalFlowConfig,
                 align_corners: bool, iters_left: int) -> None:
    """Stop the active pairs of ``cur`` (in place) that cannot pass the score test in time:
    a failing score (CCS or SCR at the current poses), extrapolated linearly at its rate
    since the previous check over the ``iters_left`` iterations left, stays below its
    threshold. They are iterating in a wrong basin and would come back failed at the
    iteration cap. The first check only records the scores. ``motion``: the packed
    current poses ``(b, 5, 4)``."""
    grid = _grid(pairs, motion)
    rows = torch.cat([_sample(pairs.c_map, grid, "bilinear", align_corners),
                      _sample(pairs.l_map, grid, "bilinear", align_corners)], 1)  # (b, 2, K)
    inside = (_inside(grid) & pairs.valid).cpu().numpy()
    c_tar, l_tar = rows.cpu().numpy().astype(np.float64).transpose(1, 0, 2)
    now = np.stack(_scores(pairs.curvature.cpu().numpy().astype(np.float64), l_tar, (c_tar > 0.5) & inside), 1)
    thresholds = np.array([config.ccs_threshold, config.scr_threshold])
    with np.errstate(invalid="ignore"):  # NaN scores (nothing shared) cannot pass
        reach = now + np.maximum(now - cur.checked, 0.0) * (iters_left / config.stall_check_iters)
        stall = cur.active & np.isfinite(cur.checked).all(1) & ~(reach >= thresholds).all(1)
    cur.checked = np.where(cur.active[:, None], now, cur.checked)
    cur.stalled |= stall
    cur.active &= ~stall


def _linearise(pairs: _Pairs, motion: torch.Tensor, align_corners: bool) -> tuple[torch.Tensor, ...]:
    """Normal equations of the residual ``R^T N_tar(x') - n`` at the current poses.

    Args:
        pairs: the pairs.
        motion: ``(b, 5, 4)`` poses packed by :func:`_motion`.

    Returns:
        ``ata (b, 5, 5)`` float64, ``atb (b, 5)`` in the working dtype (accumulated by
        one product; the host widens it) and the shared-sample count ``(b,)``.
    """
    b, k = motion.shape[0], pairs.points_t.shape[2]
    grid = _grid(pairs, motion)
    near = _sample(pairs.c_map, grid, "nearest", align_corners).view(b, k)
    shared = (near > 0.5) & _inside(grid) & pairs.valid
    res = torch.bmm(motion[:, 2:, :3], _sample(pairs.n_map, grid, "bilinear", align_corners)) - pairs.normals_t
    atb = _bmv(pairs.jacobian_t, (res * as_weights(shared, res.dtype).unsqueeze(1)).view(b, 3 * k))
    return _shared_normal_matrix(pairs, shared), atb, shared.sum(1, dtype=torch.int32)


def _motion(rot: np.ndarray, txy: np.ndarray, scale: np.ndarray, offset: np.ndarray, dtype: np.dtype
            ) -> np.ndarray:
    """Pack the poses for :func:`_linearise`: ``(b, 5, 4)`` in ``dtype`` with ``[:2, :3]``
    taking a metric point to grid coordinates (``R[:2] * scale``), ``[:2, 3]`` the grid
    offset ``txy * scale + offset`` (``offset`` ``(b, 2)``: the targets' windows,
    :func:`_grid_offsets`) and ``[2:, :3]`` the rotation's transpose ``R^T``."""
    out = np.zeros((len(rot), 5, 4), dtype=dtype)
    out[:, :2, :3] = rot[:, :2] * scale[:, None]
    out[:, :2, 3] = txy * scale + offset
    out[:, 2:, :3] = rot.transpose(0, 2, 1)
    return out


def _host_dtype(dtype: torch.dtype) -> np.dtype:
    """The numpy dtype of a torch dtype (host arrays packed for the device)."""
    return torch.empty((), dtype=dtype).numpy().dtype


def _ridge(ata_full: torch.Tensor) -> np.ndarray:
    """``1e-12`` of each pair's largest diagonal entry on the diagonal, host float64.
    ``(b, 5, 5)`` -> ``(b, 5, 5)``."""
    diag = ata_full.diagonal(dim1=1, dim2=2).cpu().numpy()
    return 1e-12 * diag.max(1)[:, None, None] * np.eye(5)


def _gauss_newton(st: _State, pairs: _Pairs, scale: np.ndarray, align_corners: bool, config: NormalFlowConfig,
                  max_iters: int, min_iters: int, tol_scale: float) -> _State:
    """Inverse-compositional Gauss-Newton iterations of one level (method.md 4.4) for the
    active pairs of ``st``: per-sample work in torch on the maps' device, the 5x5 solves
    and pose updates in host float64. The working set shrinks as pairs finish (halved
    at a time, so copies stay bounded); a finished pair's state is frozen."""
    ids = np.flatnonzero(st.active)
    out = _State(*(getattr(st, f.name).copy() for f in fields(st)))
    if len(ids) == 0:
        return out
    if len(ids) < len(st.active):
        pairs = pairs.take(ids)
    cur, ridge = st.take(ids), _ridge(pairs.ata_full)
    dev = pairs.points_t.device
    host_dt = _host_dtype(pairs.points_t.dtype)
    tol2 = (np.array([config.rot_tol, config.trans_tol_m]) * tol_scale) ** 2
    check = config.stall_check_iters if config.check_scores and pairs.l_map is not None else 0
    for i in range(max_iters):
        motion = torch.from_numpy(_motion(cur.rot, cur.txy, scale, pairs.offset, host_dt)).to(dev)
        if check and i > 0 and i % check == 0:
            _stall_check(cur, pairs, motion, config, align_corners, max_iters - i)
            if not cur.active.any():
                break
        ata, atb, n_shared = (x.cpu().numpy() for x in _linearise(pairs, motion, align_corners))
        atb = atb.astype(np.float64)
        if not np.isfinite(atb).all():  # finite Jacobians and poses: the sampled target normals
            raise _target_error("normals")
        cur.ata = ata
        delta, solved = _solve(ata, atb, ridge, config.lm_damping)
        # too few shared samples, or an unsolvable step: lost (the pose stays as it was)
        bad = cur.active & ((n_shared < config.min_shared) | ~solved)
        cur.lost |= bad
        cur.active &= ~bad
        delta[~cur.active] = 0.0
        # T <- T dT^-1 with dT = [R(w) | (tx, ty, 0)], R(w) = Rz Ry Rx; tz stays 0 here
        cur.rot = cur.rot @ euler_to_matrix(delta[:, :3]).transpose(0, 2, 1)
        cur.txy = cur.txy - (cur.rot[:, :2, :2] @ delta[:, 3:, None])[..., 0]
        cur.iterations += cur.active
        if i + 1 >= min_iters:
            step = ((delta[:, :3] ** 2).sum(1) < tol2[0]) & ((delta[:, 3:] ** 2).sum(1) < tol2[1])
            cur.converged |= cur.active & step
            cur.active &= ~step
            n_active = int(cur.active.sum())
            if n_active == 0:
                break
            if 2 * n_active <= len(ids):  # drop the finished pairs
                out.put(ids, cur)
                keep = np.flatnonzero(cur.active)
                ids, cur, pairs = ids[keep], cur.take(keep), pairs.take(keep)
                ridge = _ridge(pairs.ata_full)
    out.put(ids, cur)
    return out


def register_prepared(
    prep: PreparedReference,
    tar: Frame | WindowBatch,
    init_tar_T_ref: torch.Tensor | None = None,
    config: NormalFlowConfig | None = None,
) -> RegistrationResult:
    """Register ``B`` targets to prepared references (one reference, broadcast, or ``B``).

    Args:
        prep: from :func:`prepare_reference`, batch 1 or ``B``.
        tar: ``B`` target frames of the same size and scale, full-size or in windows
            (:func:`~tactile_slam.geometry.frame.window_batch` aligned to
            :func:`window_multiple` of ``config``): the same result up to rounding, with
            less to read when contacts cover a fraction of the image.
        init_tar_T_ref: ``(B, 4, 4)`` or ``(4, 4)`` initial tar_T_ref (metres; its tz
            is ignored), identity if ``None``.
        config: NormalFlow settings; must match the one used for ``prep``.

    Returns:
        a :class:`RegistrationResult` of ``B`` pairs; failures are reported, not raised.
        With ``config.fallback_factors``, pairs that fail are solved once more from the
        same initial pose through coarse levels of those factors, and those that still
        fail (with ``fallback_shift_search``) from the initial pose moved to the contacts'
        best-aligning shift; a retry replaces the failure only if it passes every check.

    The work runs under ``torch.inference_mode`` (no autograd bookkeeping: about 10 %
    of a pair's time); the result is returned as ordinary tensors.
    """
    with torch.inference_mode():
        res = _register_prepared(prep, tar, init_tar_T_ref, config)
    return res.clone()


def _register_prepared(prep: PreparedReference, tar: Frame | WindowBatch, init_tar_T_ref, config
                       ) -> RegistrationResult:
    """:func:`register_prepared` without the copy out of inference mode."""
    config = config or NormalFlowConfig()
    _check_config(config, prep.shape)
    if prep.settings and prep.settings != reference_settings(config):
        raise RegistrationError(
            "the reference was prepared with other sample or level settings than this config's "
            f"({prep.settings} against {reference_settings(config)}): prepare it with this config")
    tar = _full(tar, "target", windows=True)
    b = len(tar)
    if b == 0:
        raise RegistrationError("empty target batch")
    if len(prep) not in (1, b):
        raise RegistrationError(f"{len(prep)} references cannot be paired with {b} targets")
    if tuple(tar.shape) != tuple(prep.shape):
        raise RegistrationError(f"target size {tuple(tar.shape)} differs from reference size {prep.shape}")
    if abs(tar.mm_per_px / 1000.0 - prep.m_per_px) > 1e-12:
        raise RegistrationError(f"target scale {tar.mm_per_px} mm/px differs from the reference's")
    if isinstance(tar, WindowBatch):
        m = window_multiple(config)
        if (torch.tensor(tar.maps.shape) % m).any() or (tar.origins % m).any():
            raise RegistrationError(f"target windows must be aligned to {m} px (window_multiple of the config)")
    init = np.eye(4)[None] if init_tar_T_ref is None else _host_init(init_tar_T_ref, b)
    # one reference: its samples are shared by the batch; chunks would only add calls
    step = b if len(prep) == 1 else _chunk_pairs(config, prep.points_t.shape[2], prep.device)
    if b <= step:
        return _register_with_fallback(prep, tar, init, config)
    return RegistrationResult.cat([
        _register_with_fallback(prep[a:a + step], tar[a:a + step], init if len(init) == 1 else init[a:a + step],
                                config)
        for a in range(0, b, step)])


def _chunk_pairs(config: NormalFlowConfig, k: int, device: torch.device) -> int:
    """Pairs solved together: ``config.cpu_chunk_samples // k`` (at least 1) on the CPU,
    unbounded elsewhere or when it is 0 (``k``: samples per pair)."""
    if device.type != "cpu" or config.cpu_chunk_samples == 0:
        return np.iinfo(np.int64).max
    return max(1, config.cpu_chunk_samples // max(k, 1))


def _register_with_fallback(prep: PreparedReference, tar: Frame | WindowBatch, init: np.ndarray,
                            config: NormalFlowConfig) -> RegistrationResult:
    """Solve (:func:`_register_levels`), then retry the failures through
    ``config.fallback_factors`` if set: from the same start, then (``fallback_shift_search``)
    from the start moved to the in-plane shift that best aligns the two contacts
    (:func:`~tactile_slam.registration.shift.correlation_shift`). Arguments already
    checked; ``init`` host float64 ``(1 or B, 4, 4)``."""
    res = _register_levels(prep, tar, init, config)
    if not config.fallback_factors:
        return res
    starts = [lambda ids: init[ids] if len(init) > 1 else init]
    if config.fallback_shift_search:
        starts.append(lambda ids: _shifted_starts(prep, tar, init, ids))
    for start in starts:
        ids = np.flatnonzero(~res.ok.cpu().numpy())
        if len(ids) == 0:
            break
        retry = _register_levels(prep.retry_levels(ids if len(prep) > 1 else None, config.fallback_factors,
                                                   config.jacobian),
                                 tar[torch.from_numpy(ids).to(tar.device)], start(ids), config)
        res = _take_successes(res, ids, retry)
    return res


def _shifted_starts(prep: PreparedReference, tar: Frame | WindowBatch, init: np.ndarray, ids: np.ndarray
                    ) -> np.ndarray:
    """``init`` of the pairs ``ids`` with its ``(x, y)`` translation replaced by the contacts'
    best-aligning shift (rotation and ``z`` kept). ``(n, 4, 4)`` host float64."""
    part = tar[torch.from_numpy(ids).to(tar.device)]
    part = part.expand() if isinstance(part, WindowBatch) else part
    ref = prep if len(prep) == 1 else prep[torch.from_numpy(ids).to(prep.device)]
    shift = correlation_shift(ref.normals_map, ref.contact, part.normals.to(prep.device), part.contact.to(prep.device))
    out = np.array(np.broadcast_to(init[ids] if len(init) > 1 else init, (len(ids), 4, 4)))
    out[:, :2, 3] = shift.cpu().numpy() * prep.m_per_px
    return out


def _take_successes(res: RegistrationResult, ids: np.ndarray, retry: RegistrationResult) -> RegistrationResult:
    """``res`` with the pairs ``ids`` replaced by ``retry``'s results where those passed."""
    take = torch.zeros(len(res.ok), dtype=torch.bool, device=res.ok.device)
    take[torch.from_numpy(ids).to(take.device)] = retry.ok
    merged = res.clone()
    for f in fields(RegistrationResult):
        getattr(merged, f.name)[take] = getattr(retry, f.name)[retry.ok]
    return merged


def _register_levels(prep: PreparedReference, tar: Frame | WindowBatch, init: np.ndarray,
                     config: NormalFlowConfig) -> RegistrationResult:
    """Solve the levels of ``prep`` (coarse to fine) from ``init`` ``(1 or B, 4, 4)``,
    then score (:func:`_finish`)."""
    b = len(tar)
    dev, dt = prep.device, prep.dtype
    origins = np.zeros((b, 2))
    if isinstance(tar, WindowBatch):
        tar, origins = tar.maps, tar.origins.numpy().astype(np.float64)
    n_map = tar.normals.to(device=dev, dtype=dt).permute(0, 3, 1, 2)  # a view: no copy
    c_map = as_weights(tar.contact.to(dev), dt).unsqueeze(1)
    flags = np.zeros(b, dtype=bool)
    st = _State(np.broadcast_to(init[:, :3, :3], (b, 3, 3)).copy(), np.broadcast_to(init[:, :2, 3], (b, 2)).copy(),
                ~flags, flags.copy(), flags.copy(), np.zeros(b, dtype=np.int64), np.zeros((b, 5, 5)), flags.copy(),
                np.full((b, 2), np.nan))
    l_map = tar.curvature.to(device=dev, dtype=dt).unsqueeze(1)
    for lvl in prep.levels:
        f = lvl.factor
        coarse = f > 1  # coarse levels: block-averaged target maps, image-edge grid convention
        offset = _grid_offsets(prep.shape, tar.shape, origins, align_corners=not coarse)
        pairs = _Pairs(prep.points_t, prep.valid, lvl.normals_t, lvl.jacobian_t, lvl.jtj, lvl.ata_full,
                       F.avg_pool2d(n_map, f) if coarse else n_map, F.avg_pool2d(c_map, f) if coarse else c_map,
                       offset, None if coarse else prep.curvature, None if coarse else l_map)
        scale = _grid_scale(tar.shape, prep.m_per_px, align_corners=not coarse)
        if coarse:
            st = _gauss_newton(st, pairs, scale, False, config, config.coarse_max_iters, 1, float(f))
            st.active, st.converged = ~st.lost, np.zeros_like(st.lost)
        else:
            st = _gauss_newton(st, pairs, scale, True, config, config.max_iters, config.min_iters, 1.0)
    maps = (tar.height.to(device=dev, dtype=dt).unsqueeze(1), l_map, c_map)
    return _finish(prep, maps, st, config, scale, offset)


def _host_init(init_tar_T_ref, b: int) -> np.ndarray:
    """A user's initial poses as host float64 ``(1 or b, 4, 4)``, checked."""
    init = torch.as_tensor(init_tar_T_ref, dtype=torch.float64).detach().cpu().numpy()
    if init.ndim == 2:
        init = init[None]
    if init.shape[1:] != (4, 4) or init.shape[0] not in (1, b):
        raise RegistrationError(f"init_tar_T_ref must be (B, 4, 4) or (4, 4), got {tuple(init_tar_T_ref.shape)}")
    if not np.isfinite(init).all():
        raise RegistrationError("init_tar_T_ref contains NaN or Inf")
    return init


def _finish(prep: PreparedReference, maps, st: _State, config: NormalFlowConfig, scale: np.ndarray,
            offset: np.ndarray) -> RegistrationResult:
    """tz from the height difference, CCS/SCR, degeneracy, and the ok flag.

    ``maps``: the targets' ``(B, 1, h, w)`` height, curvature and contact (windows at
    grid ``offset`` ``(B, 2)``); the poses are ``st.rot``, ``st.txy`` (tz is set here).
    The samples are taken on the maps' device in one pass; the reductions over them run
    on the host in float64."""
    b = len(st.rot)
    h_map, l_map, c_map = maps
    pack = _motion(st.rot, st.txy, scale, offset, _host_dtype(prep.dtype))[:, :3]  # rows: grid x, grid y, then
    pack[:, 2, :3] = st.rot[:, 2]  # (R P)_z
    pack = torch.from_numpy(pack).to(prep.device)
    proj = torch.baddbmm(pack[:, :, 3:], pack[:, :, :3], prep.points_t.expand(b, -1, -1))  # (B, 3, K)
    grid = proj[:, :2].mT
    inside = (_inside(grid) & prep.valid).unsqueeze(1)
    rows = torch.cat([_sample(c_map, grid, "nearest"), _sample(h_map, grid, "bilinear"),
                      _sample(c_map, grid, "bilinear"), _sample(l_map, grid, "bilinear"), proj[:, 2:], inside], 1)
    rows = rows.cpu().numpy().astype(np.float64)
    if not np.isfinite(rows).all():
        raise _target_error("height or curvature")
    near, h_tar, c_tar, l_tar, z, inside = rows.transpose(1, 0, 2)  # (B, K) each
    inside = inside > 0.5
    l_ref = prep.curvature.cpu().numpy().astype(np.float64)  # (B or 1, K)
    with np.errstate(divide="ignore", invalid="ignore"):  # undefined scores are NaN and fail below
        # tz: mean of s*H_tar - (R P)_z over samples landing in the target contact (nearest)
        vz = (near > 0.5) & inside
        n_z = vz.sum(1)
        tz_ok = n_z > 0
        tz = np.where(tz_ok, np.where(vz, h_tar * prep.m_per_px - z, 0.0).sum(1) / np.maximum(n_z, 1), 0.0)
    # CCS and SCR over the samples landing in the target contact (bilinear)
    shf = (c_tar > 0.5) & inside
    ccs, scr = _scores(l_ref, l_tar, shf)
    # degenerate: eigenvalue ratio of the normal equations, translations scaled by the
    # samples' RMS spread so that both parts measure displacement
    sc = np.ones((b, 5))
    sc[:, 3:] = prep.spread.cpu().numpy()[:, None]
    scaled = st.ata * sc[:, :, None] * sc[:, None, :]
    finite = np.isfinite(scaled).all((1, 2))  # numpy's eigvalsh raises on NaN; such a pair is degenerate
    eig = np.linalg.eigvalsh(np.where(finite[:, None, None], scaled, np.eye(5)))
    with np.errstate(divide="ignore", invalid="ignore"):
        conditioning = np.where(finite & (eig[:, -1] > 0), eig[:, 0] / eig[:, -1], 0.0)
    degenerate = ~finite | ~(eig[:, 0] > config.degenerate_eig * eig[:, -1])
    ok = ~st.lost & ~st.stalled & ~degenerate & tz_ok
    if config.check_scores:
        ok &= _passes(ccs, scr, config)
    T = np.zeros((b, 4, 4))
    T[:, :3, :3], T[:, :2, 3], T[:, 2, 3], T[:, 3, 3] = st.rot, st.txy, tz, 1.0
    out = dict(tar_T_ref=T, ccs=ccs, scr=scr, n_shared=shf.sum(1).astype(np.int64), iterations=st.iterations,
               converged=st.converged, ok=ok, conditioning=conditioning)
    return RegistrationResult(**{name: torch.from_numpy(np.ascontiguousarray(v)).to(prep.device)
                                 for name, v in out.items()})


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
    config = config or NormalFlowConfig()
    _check_config(config)
    ref, tar = _full(ref, "reference"), _full(tar, "target", windows=True)
    b = len(ref)
    if b > 1:
        k = config.n_samples or int(ref.contact.reshape(b, -1).sum(1).max())  # samples per pair (at most)
        step = _chunk_pairs(config, k, ref.normals.device)
    if b <= 1 or b <= step:  # one chunk (or one reference for every target)
        return register_prepared(prepare_reference(ref, config, dtype), tar, init_tar_T_ref, config)
    if len(tar) != b:
        raise RegistrationError(f"{b} references cannot be paired with {len(tar)} targets")
    # each chunk prepared just before it is solved, so its references are still in cache
    init = None if init_tar_T_ref is None else _host_init(init_tar_T_ref, b)
    return RegistrationResult.cat([
        register_prepared(prepare_reference(ref[a:a + step], config, dtype), tar[a:a + step],
                          None if init is None else init if len(init) == 1 else init[a:a + step], config)
        for a in range(0, b, step)])


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
