"""Tracking metrics (method.md section 9.1).

Inputs are trajectories ``start_T_curr`` ``(T, 4, 4)`` in metres relative to the same
start frame (element 0 is the identity); NaN rows are frames without an estimate.

* :func:`per_axis_errors` / :func:`per_axis_mae`: exactly as the NormalFlow experiment
  scripts compute them: translation x1000 (mm); rotation as scipy's extrinsic ``'zxy'``
  Euler angles in degrees, ``(theta_z, theta_x, theta_y)`` re-ordered to
  ``(theta_x, theta_y, theta_z)``; absolute difference per component, no angle wrapping,
  no alignment; frame 0 skipped.
* :func:`ate`: RMSE of the translation error (mm) and RMS geodesic rotation error (deg),
  without alignment (the start frame is shared) or after an SE(3) Umeyama alignment.
* :func:`rpe`: relative pose error over a fixed number of frames or a fixed travel.
* :func:`motion_range`: cumulative motion per axis (the paper's Table I quantity) over
  steps between consecutive evaluated frames, Euler angle changes unwrapped.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from tactile_slam.eval.trajectory import TrajectoryError, check_trajectory, valid_mask

AXES = ("x_mm", "y_mm", "z_mm", "rx_deg", "ry_deg", "rz_deg")


def _pair(est: np.ndarray, gt: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    est, gt = check_trajectory(est, "estimate"), check_trajectory(gt, "ground truth")
    if est.shape != gt.shape:
        raise TrajectoryError(f"estimate {est.shape} and ground truth {gt.shape} differ in length")
    if not valid_mask(gt).all():
        raise TrajectoryError("ground truth has frames without a pose")
    return est, gt


def pose_vector(poses: np.ndarray) -> np.ndarray:
    """``(T, 4, 4)`` -> ``(T, 6)``: ``[x, y, z]`` mm and ``[theta_x, theta_y, theta_z]``
    degrees from scipy's extrinsic ``'zxy'`` Euler angles (NormalFlow's convention).
    NaN rows stay NaN."""
    poses = np.asarray(poses, dtype=np.float64)
    out = np.full((len(poses), 6), np.nan)
    ok = valid_mask(poses)
    if ok.any():
        out[ok, :3] = poses[ok, :3, 3] * 1000.0
        zxy = Rotation.from_matrix(poses[ok, :3, :3]).as_euler("zxy", degrees=True)
        out[ok, 3:] = zxy[:, [1, 2, 0]]
    return out


def per_axis_errors(est: np.ndarray, gt: np.ndarray) -> np.ndarray:
    """Absolute per-axis errors ``(T, 6)`` (mm, deg; see :func:`pose_vector`); NaN where
    the estimate is missing."""
    est, gt = _pair(est, gt)
    return np.abs(pose_vector(est) - pose_vector(gt))


def per_axis_mae(est: np.ndarray, gt: np.ndarray, frames: np.ndarray | None = None) -> dict[str, float]:
    """Per-axis mean absolute error over frames ``1..T-1`` that have an estimate.

    Args:
        est, gt: ``(T, 4, 4)`` ``start_T_curr``.
        frames: optional ``(T,)`` bool restricting the frames (e.g. those in contact).

    Returns:
        ``{"x_mm", "y_mm", "z_mm", "rx_deg", "ry_deg", "rz_deg", "n_frames"}``.
    """
    err = per_axis_errors(est, gt)
    use = valid_mask(est)
    use[0] = False
    if frames is not None:
        use &= np.asarray(frames, dtype=bool)
    out = {k: float(err[use, i].mean()) if use.any() else float("nan") for i, k in enumerate(AXES)}
    out["n_frames"] = int(use.sum())
    return out


def geodesic_deg(r_a: np.ndarray, r_b: np.ndarray) -> np.ndarray:
    """Angle of ``r_a^T r_b`` in degrees, ``(..., 3, 3)`` x2 -> ``(...)``; the cosine is
    clipped to [-1, 1]."""
    tr = np.einsum("...ji,...ji->...", r_a, r_b)
    return np.degrees(np.arccos(np.clip((tr - 1.0) / 2.0, -1.0, 1.0)))


def umeyama(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """Rigid transform (no scale) minimising ``sum |dst - (R src + t)|^2``.

    Args:
        src, dst: ``(N, 3)`` corresponding points, N >= 3 not collinear.

    Returns:
        ``(4, 4)`` ``dst_T_src``.
    """
    if len(src) < 3:
        raise ValueError(f"alignment needs at least 3 points, got {len(src)}")
    mu_s, mu_d = src.mean(0), dst.mean(0)
    cov = (dst - mu_d).T @ (src - mu_s) / len(src)
    u, _, vt = np.linalg.svd(cov)
    s = np.eye(3)
    if np.linalg.det(u) * np.linalg.det(vt) < 0:
        s[2, 2] = -1
    out = np.eye(4)
    out[:3, :3] = u @ s @ vt
    out[:3, 3] = mu_d - out[:3, :3] @ mu_s
    return out


def ate(est: np.ndarray, gt: np.ndarray, align: bool = False, frames: np.ndarray | None = None) -> dict[str, float]:
    """Absolute trajectory error over frames with an estimate (and in ``frames``).

    Returns:
        ``{"trans_rmse_mm", "rot_rms_deg", "n_frames"}``; with ``align`` the estimate is
        first moved by the SE(3) (Umeyama, no scale) that best fits its positions to the
        ground truth. Errors are NaN when no frame is usable, or with ``align`` when
        fewer than 3 are (the alignment is undefined), e.g. a run split into tiny groups.
    """
    est, gt = _pair(est, gt)
    use = valid_mask(est)
    if frames is not None:
        use &= np.asarray(frames, dtype=bool)
    e, g = est[use], gt[use]
    if len(e) == 0 or (align and len(e) < 3):
        return {"trans_rmse_mm": float("nan"), "rot_rms_deg": float("nan"), "n_frames": int(len(e))}
    if align:
        e = umeyama(e[:, :3, 3], g[:, :3, 3]) @ e
    dt = np.linalg.norm(e[:, :3, 3] - g[:, :3, 3], axis=1) * 1000.0
    dr = geodesic_deg(e[:, :3, :3], g[:, :3, :3])
    return {"trans_rmse_mm": float(np.sqrt(np.mean(dt**2))), "rot_rms_deg": float(np.sqrt(np.mean(dr**2))),
            "n_frames": int(len(e))}


def travel_pairs(gt: np.ndarray, distance_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """Index pairs ``(i, j)``: ``j`` is the first frame after which the ground-truth
    sensor has travelled ``distance_mm`` (path length of its positions) since ``i``."""
    step = np.linalg.norm(np.diff(gt[:, :3, 3], axis=0), axis=1) * 1000.0
    cum = np.concatenate([[0.0], np.cumsum(step)])
    j = np.searchsorted(cum, cum + distance_mm, side="left")
    keep = j < len(gt)
    return np.nonzero(keep)[0], j[keep]


def rpe(est: np.ndarray, gt: np.ndarray, delta: int | None = 1, distance_mm: float | None = None,
        frames: np.ndarray | None = None) -> dict[str, float]:
    """Relative pose error between frames ``delta`` apart, or ``distance_mm`` of
    ground-truth travel apart (give exactly one).

    For each pair the error is ``inv(gt_i^-1 gt_j) (est_i^-1 est_j)``; pairs need an
    estimate at both ends (and both in ``frames``).

    Returns:
        ``{"trans_rmse_mm", "rot_rms_deg", "n_pairs"}``.
    """
    est, gt = _pair(est, gt)
    if (delta is None) == (distance_mm is None):
        raise ValueError("give exactly one of delta and distance_mm")
    if distance_mm is None:
        if delta < 1:
            raise ValueError(f"delta must be >= 1, got {delta}")
        i = np.arange(len(gt) - delta)
        j = i + delta
    else:
        i, j = travel_pairs(gt, distance_mm)
    use = valid_mask(est)
    if frames is not None:
        use &= np.asarray(frames, dtype=bool)
    ok = use[i] & use[j]
    i, j = i[ok], j[ok]
    if len(i) == 0:
        return {"trans_rmse_mm": float("nan"), "rot_rms_deg": float("nan"), "n_pairs": 0}
    rel_e = np.linalg.inv(est[i]) @ est[j]
    rel_g = np.linalg.inv(gt[i]) @ gt[j]
    err = np.linalg.inv(rel_g) @ rel_e
    dt = np.linalg.norm(err[:, :3, 3], axis=1) * 1000.0
    dr = geodesic_deg(err[:, :3, :3], np.eye(3))
    return {"trans_rmse_mm": float(np.sqrt(np.mean(dt**2))), "rot_rms_deg": float(np.sqrt(np.mean(dr**2))),
            "n_pairs": int(len(i))}


def motion_range(start_T_curr: np.ndarray, frames: np.ndarray | None = None) -> dict[str, float]:
    """Cumulative motion per axis (mm, deg): over each pair of consecutive frames that are
    both in ``frames`` (``(T,)`` bool; all when ``None``) and both have a pose, the sum of
    the absolute change of each :func:`pose_vector` component.

    Steps across frames outside ``frames`` (the lifts between touches) or without a pose
    are left out, and an angle change is taken into (-180, 180] deg, so crossing the
    Euler angles' +-180 deg wrap counts the rotation made, not 360 deg minus it. Near
    the zxy gimbal lock (``theta_x`` at +-90 deg) ``theta_y`` and ``theta_z`` still change
    fast for a small rotation.
    """
    v = pose_vector(check_trajectory(start_T_curr))
    use = valid_mask(v)
    if frames is not None:
        if np.shape(frames) != use.shape:
            raise TrajectoryError(f"frames {np.shape(frames)} do not match {len(use)} poses")
        use &= np.asarray(frames, dtype=bool)
    d = np.diff(v, axis=0)[use[:-1] & use[1:]]
    d[:, 3:] = 180.0 - (180.0 - d[:, 3:]) % 360.0
    return {k: float(np.abs(d[:, i]).sum()) for i, k in enumerate(AXES)}


def frame_steps(poses: np.ndarray, frames: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Motion between consecutive frames: rotation angle (deg) and translation (mm) of
    ``inv(T_i) T_{i+1}`` for poses ``(T, 4, 4)`` metres, ``(T - 1,)`` each; NaN where either
    frame is outside ``frames`` (``(T,)`` bool) or has no pose."""
    T = check_trajectory(poses)
    rel = np.linalg.inv(T[:-1]) @ T[1:]
    deg = geodesic_deg(rel[:, :3, :3], np.eye(3))
    mm = np.linalg.norm(rel[:, :3, 3], axis=1) * 1000.0
    use = np.isfinite(deg) & np.isfinite(mm)
    if frames is not None:
        f = np.asarray(frames, dtype=bool)
        use &= f[:-1] & f[1:]
    return np.where(use, deg, np.nan), np.where(use, mm, np.nan)


def tracking_report(est: np.ndarray, gt: np.ndarray, frames: np.ndarray | None = None,
                    travel_mm: float = 5.0) -> dict:
    """Every tracking metric of one trial (see the module docstring).

    Args:
        est, gt: ``(T, 4, 4)`` ``start_T_curr``.
        frames: optional ``(T,)`` bool, the frames to evaluate (e.g. ground-truth contact).
        travel_mm: travel of the distance-based RPE.
    """
    est, gt = _pair(est, gt)
    sel = np.ones(len(gt), bool) if frames is None else np.asarray(frames, dtype=bool)
    has = valid_mask(est)
    return {
        "per_axis_mae": per_axis_mae(est, gt, sel),
        "ate": ate(est, gt, False, sel),
        "ate_aligned": ate(est, gt, True, sel),
        "rpe_1": rpe(est, gt, 1, frames=sel),
        "rpe_25": rpe(est, gt, 25, frames=sel),
        f"rpe_{travel_mm:g}mm": rpe(est, gt, None, travel_mm, frames=sel),
        "estimated_fraction": float(has[sel].mean()) if sel.any() else float("nan"),
        "motion_range": motion_range(gt, sel),
    }
