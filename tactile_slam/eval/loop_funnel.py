"""Where true revisits between sessions are lost on the way to a loop.

Loop closure joins two sessions only through a pair of keyframes, one of each, that
touch the same surface. For every such pair of a run (at the true poses they share at
least ``min_overlap_mm2``, :func:`~tactile_slam.eval.loop_metrics.share_patch`), this
counts how far loop detection's chain (method.md 6.2-6.4) could carry it, each stage
measured on its own against the truth:

* ``keypoints``: both keyframes have at least ``min_sift_inliers`` SIFT keypoints;
* ``repeatable``: at least ``min_sift_inliers`` of the earlier keyframe's keypoints land,
  at the true pose, within ``px_tol`` of a keypoint of the later one (the detector found
  the same places in both);
* ``true_matches``: at least ``min_sift_inliers`` of the cross-checked descriptor
  matches are such pairs (the descriptors recognise them);
* ``matched``: SIFT matching and 2-D RANSAC make the pair a loop candidate;
* ``verified``: of those, NormalFlow from the RANSAC guess passes the loop CCS/SCR test;
* ``correct``: of those, the verified pose is within 1 degree and 0.3 mm of the truth.

The first stage where the counts fall is what limits the recall between sessions; the
candidate selection (coverage set, retrieval votes) and the back end's gate come after
and are not counted here.
"""

from __future__ import annotations

import numpy as np
import torch

from tactile_slam.config import Config
from tactile_slam.eval.loop_metrics import REACH_M, share_patch
from tactile_slam.loop.detector import LoopDetector
from tactile_slam.loop.matching import match, match_descriptors, similarity_to_se3
from tactile_slam.registration.result import pose_error

STAGES = ("pairs", "keypoints", "repeatable", "true_matches", "matched", "verified", "correct")


def _project(xy: np.ndarray, height: np.ndarray, b_T_a: np.ndarray, mm_per_px: float) -> np.ndarray:
    """Pixels ``(N, 2)`` ``(x, y)`` of frame a (with its height map ``(H, W)`` px) -> frame
    b's pixels at the pose ``b_T_a`` (metres)."""
    h, w = height.shape
    s = mm_per_px * 1e-3
    z = height[np.clip(np.round(xy[:, 1]).astype(int), 0, h - 1), np.clip(np.round(xy[:, 0]).astype(int), 0, w - 1)]
    p = np.stack([(xy[:, 0] - (w - 1) / 2) * s, (xy[:, 1] - (h - 1) / 2) * s, z * s], 1)
    q = p @ b_T_a[:3, :3].T + b_T_a[:3, 3]
    return np.stack([q[:, 0] / s + (w - 1) / 2, q[:, 1] / s + (h - 1) / 2], 1)


def revisit_funnel(keyframes: list, object_T_sensor: np.ndarray, config: Config, min_overlap_mm2: float = 5.0,
                   px_tol: float = 3.0) -> dict[str, int]:
    """Counts of the cross-session revisits that reach each stage (module docstring).

    Args:
        keyframes: a run's keyframes (``session``, ``maps``).
        object_T_sensor: ``(K, 4, 4)`` float64 true pose of each keyframe (metres).
        config: the run's configuration (curvature, SIFT, RANSAC, loop thresholds).

    Returns:
        ``{stage: count}`` for :data:`STAGES`.
    """
    if len(keyframes) != len(object_T_sensor):
        raise ValueError(f"expected one pose per keyframe, got {len(object_T_sensor)} for {len(keyframes)}")
    out = dict.fromkeys(STAGES, 0)
    if not keyframes:
        return out
    det = LoopDetector(config)
    frames = [k.frame for k in keyframes]
    height = np.stack([f.height[0].cpu().numpy() for f in frames])
    contact = np.stack([f.contact[0].cpu().numpy() for f in frames])
    feats = [det.extract(k) for k in keyframes]
    s = config.sensor.mm_per_px
    need = det.ransac.min_inliers
    for t in range(len(keyframes)):
        for r in range(t):
            if keyframes[r].session == keyframes[t].session:
                continue
            if np.linalg.norm(object_T_sensor[r, :3, 3] - object_T_sensor[t, :3, 3]) > REACH_M:
                continue
            if not share_patch(r, t, object_T_sensor, height, contact, s, min_overlap_mm2):
                continue
            out["pairs"] += 1
            fr, ft = feats[r], feats[t]
            if len(fr) < need or len(ft) < need:
                continue
            out["keypoints"] += 1
            t_T_r = np.linalg.inv(object_T_sensor[t]) @ object_T_sensor[r]
            at_t = _project(fr.keypoints.numpy().astype(np.float64), height[r], t_T_r, s)
            kp_t = ft.keypoints.numpy().astype(np.float64)
            near = np.linalg.norm(at_t[:, None] - kp_t[None], axis=-1) <= px_tol
            out["repeatable"] += int(near.any(1).sum() >= need)
            m = match_descriptors(fr.descriptors, ft.descriptors)
            out["true_matches"] += int(near[m[:, 0], m[:, 1]].sum() >= need) if len(m) else 0
            sim = match(fr, ft, det.ransac)
            if sim is None:
                continue
            out["matched"] += 1
            init = similarity_to_se3(sim.M, frames[t].shape, s * 1e-3)
            res = det.verify(keyframes[t], [keyframes[r]], init[None])
            if not bool(res.ok[0]):
                continue
            out["verified"] += 1
            rot, trans = pose_error(res.tar_T_ref.cpu().double(), torch.from_numpy(t_T_r)[None])
            out["correct"] += int(float(rot) <= 1.0 and float(trans) <= 0.3)
    return out
