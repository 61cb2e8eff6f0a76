"""Loop-closure precision and recall against ground-truth relative poses.

A loop is a pair of frames ``(i, j)`` with an estimated relative pose ``i_T_j`` (the pose
of frame j's sensor in frame i's sensor frame, metres). Against the ground truth
``object_T_sensor``, ``i_T_j = inv(object_T_i) @ object_T_j``:

* a reported loop is **correct** when its translation error is at most ``trans_tol_mm``
  (0.3 mm) and its geodesic rotation error at most ``rot_tol_deg`` (1 degree); a loop whose
  keyframes include one without undeformed gel in view (``depth_known`` False in
  ``loops.json``: the height zero, and so the loop's z, is a guess, shared by the
  keyframe's odometry) is scored on its error across the sensor's axis only; a loop that
  declares its out-of-plane rotation uncertain (``tilt_sigma_deg`` in ``loops.json``: loops
  between keyframes decoded from images, which the pose graph weighs by that standard
  deviation about the sensor's x and y axes) is scored on its rotation about the sensor axis
  (``rot_tol_deg``) and its tilt error within ``max(rot_tol_deg, tilt_sigma_deg)``;
  ``correct_full_pose`` counts every loop by the geodesic test alone;
* **precision** = correct loops / reported loops;
* **recall** = ground-truth loops found by a correct report / ground-truth loops, where
  the ground-truth loops are the candidate pairs whose contact patches really overlap
  (:func:`overlap_mm2`, at least ``min_overlap_mm2``), e.g. from :func:`gt_loop_pairs`.
"""

from __future__ import annotations

import numpy as np
import torch
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from tactile_slam.eval.tracking_metrics import geodesic_deg
from tactile_slam.posegraph import se3

REACH_M = 0.03  # sensors more than 30 mm apart cannot share a patch


def _error_poses(i_T_j: np.ndarray, pairs: np.ndarray, object_T_sensor: np.ndarray,
                 depth_known: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """``(err (K, 4, 4), trans_mm (K,))``: each estimate against the truth,
    ``inv(gt_i_T_j) @ i_T_j``, and its translation error (without z where ``depth_known``
    is False). Checks the shapes and indices as :func:`relative_pose_errors` says."""
    pairs = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
    i_T_j = np.asarray(i_T_j, dtype=np.float64).reshape(-1, 4, 4)
    if len(pairs) != len(i_T_j):
        raise ValueError(f"{len(pairs)} loop pairs but {len(i_T_j)} relative poses")
    if len(pairs) and (pairs.min() < 0 or pairs.max() >= len(object_T_sensor)):
        raise ValueError("loop pair index outside the ground-truth trajectory")
    known = np.ones(len(pairs), bool) if depth_known is None else np.asarray(depth_known, bool).reshape(-1)
    if len(known) != len(pairs):
        raise ValueError(f"{len(pairs)} loop pairs but {len(known)} depth flags")
    gt = np.linalg.inv(object_T_sensor[pairs[:, 0]]) @ object_T_sensor[pairs[:, 1]]
    err = np.linalg.inv(gt) @ i_T_j
    t = err[:, :3, 3] * np.where(known[:, None], 1.0, np.array([1.0, 1.0, 0.0]))
    return err, np.linalg.norm(t, axis=1) * 1000.0


def relative_pose_errors(i_T_j: np.ndarray, pairs: np.ndarray, object_T_sensor: np.ndarray,
                         depth_known: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Errors of estimated relative poses ``(K, 4, 4)`` for ``pairs`` ``(K, 2)`` against
    ground truth ``(T, 4, 4)`` ``object_T_sensor``; where ``depth_known`` ``(K,)`` bool is
    False the translation error leaves out its z (frame j's sensor axis). Returns
    ``(trans_mm (K,), rot_deg (K,))``."""
    err, trans = _error_poses(i_T_j, pairs, object_T_sensor, depth_known)
    return trans, geodesic_deg(err[:, :3, :3], np.eye(3))


def loop_flags(loops: list[dict]) -> tuple[np.ndarray, np.ndarray]:
    """What ``loops.json`` records declare about their own measurement:
    ``(depth_known (K,) bool, tilt_sigma_deg (K,) float, NaN where not declared)``."""
    known = np.array([lp.get("depth_known", True) for lp in loops], dtype=bool)
    sigma = np.array([np.nan if lp.get("tilt_sigma_deg") is None else lp["tilt_sigma_deg"] for lp in loops],
                     dtype=np.float64)
    return known, sigma


def tilt_twist_deg(rot: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Swing-twist split of rotations ``(..., 3, 3)`` about the sensor's z axis: the tilt
    (the angle the rotation turns the z axis by) and the twist (the remaining rotation
    about z), both ``(...,)`` degrees in [0, 180] (:func:`~tactile_slam.posegraph.se3.tilt_deg`,
    :func:`~tactile_slam.posegraph.se3.twist_deg`)."""
    r = torch.from_numpy(np.asarray(rot, dtype=np.float64))
    return se3.tilt_deg(r).numpy(), se3.twist_deg(r).numpy()


def within_tolerance(rot_deg: np.ndarray, tilt_deg: np.ndarray, twist_deg: np.ndarray, trans_mm: np.ndarray,
                     tilt_sigma_deg: np.ndarray, rot_tol_deg: float, trans_tol_mm: float) -> np.ndarray:
    """The module's rule for a loop's error (or any relative-pose difference), ``(K,)``
    arrays each: the translation within ``trans_tol_mm`` and, where ``tilt_sigma_deg`` is
    NaN, the geodesic rotation within ``rot_tol_deg``; where a tilt sigma is declared, the
    twist within ``rot_tol_deg`` and the tilt within ``max(rot_tol_deg, sigma)``. NaN
    errors are outside. -> ``(K,)`` bool."""
    near = trans_mm <= trans_tol_mm
    declared = near & (twist_deg <= rot_tol_deg) & (tilt_deg <= np.fmax(rot_tol_deg, tilt_sigma_deg))
    return np.where(np.isnan(tilt_sigma_deg), near & (rot_deg <= rot_tol_deg), declared)


def loop_precision_recall(pairs: np.ndarray, i_T_j: np.ndarray, object_T_sensor: np.ndarray,
                          gt_pairs: np.ndarray | None = None, trans_tol_mm: float = 0.3,
                          rot_tol_deg: float = 1.0, depth_known: np.ndarray | None = None,
                          tilt_sigma_deg: np.ndarray | None = None) -> dict:
    """Precision (and recall when ``gt_pairs`` is given) of reported loops.

    Args:
        pairs: ``(K, 2)`` reported frame pairs ``(i, j)``.
        i_T_j: ``(K, 4, 4)`` their estimated relative poses, metres.
        object_T_sensor: ``(T, 4, 4)`` ground truth.
        gt_pairs: ``(G, 2)`` ground-truth loops (order within a pair is ignored).
        depth_known: ``(K,)`` bool, whether both keyframes of a loop had a known height zero
            (``None``: all); the others are scored without their z error.
        tilt_sigma_deg: ``(K,)`` the out-of-plane standard deviation each loop declared
            (NaN: none; ``None``: none declared); such loops are scored as the module
            says.

    Returns:
        ``{"reported", "correct", "correct_full_pose", "precision", "gt_loops", "found",
        "recall", "trans_err_mm", "rot_err_deg"}`` (the last two: median over reported
        loops).
    """
    pairs = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
    err, dt = _error_poses(i_T_j, pairs, object_T_sensor, depth_known)
    dr = geodesic_deg(err[:, :3, :3], np.eye(3))
    full = (dt <= trans_tol_mm) & (dr <= rot_tol_deg)
    ok = full
    if tilt_sigma_deg is not None:
        sigma = np.asarray(tilt_sigma_deg, dtype=np.float64).reshape(-1)
        if len(sigma) != len(pairs):
            raise ValueError(f"{len(pairs)} loop pairs but {len(sigma)} tilt sigmas")
        tilt, twist = tilt_twist_deg(err[:, :3, :3])
        ok = within_tolerance(dr, tilt, twist, dt, sigma, rot_tol_deg, trans_tol_mm)
    out = {
        "reported": int(len(pairs)),
        "correct": int(ok.sum()),
        "correct_full_pose": int(full.sum()),
        "precision": float(ok.mean()) if len(pairs) else float("nan"),
        "trans_err_mm": float(np.median(dt)) if len(pairs) else float("nan"),
        "rot_err_deg": float(np.median(dr)) if len(pairs) else float("nan"),
    }
    if gt_pairs is not None:
        gt = {tuple(sorted(p)) for p in np.asarray(gt_pairs, dtype=np.int64).reshape(-1, 2).tolist()}
        found = gt & {tuple(sorted(p)) for p in pairs[ok].tolist()}
        out.update({"gt_loops": len(gt), "found": len(found),
                    "recall": len(found) / len(gt) if gt else float("nan")})
    return out


def overlap_mm2(height_i: np.ndarray, contact_i: np.ndarray, height_j: np.ndarray, contact_j: np.ndarray,
                j_T_i: np.ndarray, mm_per_px: float, depth_tol_mm: float = 0.3) -> float:
    """Area of frame i's contact patch that frame j also touches, in mm^2.

    Each contact pixel of i becomes its surface point (method.md section 1.2), moves into
    j's sensor frame with ``j_T_i``, and counts if it lands on a contact pixel of j whose
    height is within ``depth_tol_mm`` of it.

    Args:
        height_i, height_j: ``(H, W)`` px; contact_i, contact_j: ``(H, W)`` bool.
        j_T_i: ``(4, 4)`` metres.
    """
    h, w = contact_i.shape
    s = mm_per_px / 1000.0
    r, c = np.nonzero(contact_i)
    if len(r) == 0:
        return 0.0
    p = np.stack([(c - (w - 1) / 2) * s, (r - (h - 1) / 2) * s, height_i[r, c] * s], -1)
    q = p @ j_T_i[:3, :3].T + j_T_i[:3, 3]
    cj = np.round(q[:, 0] / s + (w - 1) / 2).astype(np.int64)
    rj = np.round(q[:, 1] / s + (h - 1) / 2).astype(np.int64)
    inside = (cj >= 0) & (cj < w) & (rj >= 0) & (rj < h)
    rj, cj, qz = rj[inside], cj[inside], q[inside, 2]
    hit = contact_j[rj, cj] & (np.abs(qz - height_j[rj, cj] * s) <= depth_tol_mm * 1e-3)
    return float(hit.sum()) * mm_per_px**2


def share_patch(i: int, j: int, object_T_sensor: np.ndarray, height: np.ndarray, contact: np.ndarray,
                 mm_per_px: float, min_overlap_mm2: float) -> bool:
    """Whether frames i and j touch at least ``min_overlap_mm2`` of the same surface, in
    both directions (:func:`overlap_mm2`)."""
    j_T_i = np.linalg.inv(object_T_sensor[j]) @ object_T_sensor[i]
    if overlap_mm2(height[i], contact[i], height[j], contact[j], j_T_i, mm_per_px) < min_overlap_mm2:
        return False
    back = overlap_mm2(height[j], contact[j], height[i], contact[i], np.linalg.inv(j_T_i), mm_per_px)
    return back >= min_overlap_mm2


def gt_loop_pairs(candidates: np.ndarray, object_T_sensor: np.ndarray, height: np.ndarray, contact: np.ndarray,
                  mm_per_px: float, min_overlap_mm2: float = 5.0, min_gap: int = 25) -> np.ndarray:
    """Ground-truth loops among candidate frames: pairs at least ``min_gap`` frames apart
    whose contact patches overlap by at least ``min_overlap_mm2`` (both directions'
    smaller value).

    Args:
        candidates: ``(K,)`` frame indices (e.g. keyframes' video indices).
        object_T_sensor: ``(T, 4, 4)``; height ``(T, H, W)`` px; contact ``(T, H, W)``.

    Returns:
        ``(G, 2)`` int64 pairs ``(i, j)`` with ``i < j``.
    """
    cand = np.unique(np.asarray(candidates, dtype=np.int64))
    centres = object_T_sensor[cand, :3, 3]
    out = []
    for a in range(len(cand)):
        for b in range(a + 1, len(cand)):
            i, j = cand[a], cand[b]
            if j - i < min_gap or np.linalg.norm(centres[a] - centres[b]) > REACH_M:
                continue
            if share_patch(i, j, object_T_sensor, height, contact, mm_per_px, min_overlap_mm2):
                out.append((i, j))
    return np.asarray(out, dtype=np.int64).reshape(-1, 2)


def joinable_groups(sessions: np.ndarray, object_T_sensor: np.ndarray, height: np.ndarray, contact: np.ndarray,
                    mm_per_px: float, min_overlap_mm2: float = 5.0) -> np.ndarray:
    """The groups an ideal loop closure could form from a run's keyframes: sessions joined
    wherever a keyframe of one and a keyframe of the other touch at least
    ``min_overlap_mm2`` of the same surface (both directions, as :func:`gt_loop_pairs`).
    Sessions that share no surface with the rest cannot be placed by touch at all, so
    this bounds the connected groups, and the reconstruction, of any system on the scan.

    Args:
        sessions: ``(K,)`` int session of each keyframe.
        object_T_sensor: ``(K, 4, 4)`` true sensor poses of the keyframes.
        height: ``(K, H, W)`` px; contact: ``(K, H, W)`` bool.

    Returns:
        ``(K,)`` int64 group label of each keyframe, ``0 .. G-1``.
    """
    sessions = np.asarray(sessions, dtype=np.int64)
    if sessions.ndim != 1 or len(sessions) != len(object_T_sensor):
        raise ValueError(f"expected one session per keyframe pose, got {sessions.shape} for {len(object_T_sensor)}")
    names, sid = np.unique(sessions, return_inverse=True)
    centres = object_T_sensor[:, :3, 3]
    joined: set[tuple[int, int]] = set()
    for i in range(len(sid)):
        near = np.linalg.norm(centres[i + 1:] - centres[i], axis=1) <= REACH_M
        for j in np.flatnonzero(near) + i + 1:
            pair = (min(sid[i], sid[j]), max(sid[i], sid[j]))
            if pair[0] == pair[1] or pair in joined:  # one shared patch joins two sessions
                continue
            if share_patch(i, j, object_T_sensor, height, contact, mm_per_px, min_overlap_mm2):
                joined.add(pair)
    pairs = np.array(sorted(joined), dtype=np.int64).reshape(-1, 2)
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(len(names), len(names)))
    _, label = connected_components(graph, directed=False)
    return label[sid].astype(np.int64)
