"""Per-frame trajectories from keyframe poses, and the run's output files.

Output folder (stable names; see ``docs/outputs.md``):

* ``poses.npy`` (T, 4, 4) float64, metres: each video frame's sensor pose in the sensor
  frame of the first contact frame of the *main* group (the connected group with the
  most frames with a pose; ties: the earliest); NaN rows for frames without contact or
  in a group not connected to it.
* ``poses_by_group.npy`` (T, 4, 4) and ``frame_group.npy`` (T,): every in-contact frame
  in the frame of its own group's first contact frame, and that group id (-1: none).
* ``trajectory_tum.txt``: the rows of ``poses.npy`` with a pose, TUM format
  (timestamp from the frame rate, translation in metres, quaternion x y z w).
* ``frames.csv``: one row per video frame: its group, session and keyframe, whether it
  became a keyframe, and the quality of its registration (CCS, SCR, conditioning).
* ``keyframes.json``, ``stats.json``, ``config.yaml``.
* ``pose_graph.png`` (:func:`write_pose_graph_png`): the back end's largest group from above.

A new run into a folder removes every :data:`RUN_OUTPUTS` file and :data:`RUN_OUTPUT_DIRS`
folder of an earlier one (:func:`clear_run_outputs`), so none is read as the new run's.

Output locations are checked before any work (:func:`check_output_folder`,
:func:`check_output_file`): a run must not compute for minutes and then find that its
results have nowhere to go. Nothing is created by the checks.
"""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from tactile_slam.viz import pose_graph_figure

if TYPE_CHECKING:
    from tactile_slam.backend import BackEnd


# what a run (and `tactile-slam eval` or `demo` of it) writes into its folder
RUN_OUTPUTS = ("poses.npy", "poses_by_group.npy", "frame_group.npy", "trajectory_tum.txt", "frames.csv",
               "keyframes.json", "stats.json", "config.yaml", "loops.json", "loops_held.json", "pose_graph.g2o",
               "pose_graph.png", "mesh_fused.ply", "mesh.ply", "mesh.png", "metrics.json", "tracking_error.png",
               "report.png")
RUN_OUTPUT_DIRS = ("groups", "preview")


def clear_run_outputs(out: Path) -> list[str]:
    """Remove an earlier run's :data:`RUN_OUTPUTS` and :data:`RUN_OUTPUT_DIRS` from ``out``
    (other files stay); returns the names removed."""
    removed = [name for name in RUN_OUTPUTS if (out / name).is_file()]
    for name in removed:
        (out / name).unlink()
    for name in RUN_OUTPUT_DIRS:
        if (out / name).is_dir():
            shutil.rmtree(out / name)
            removed.append(name + "/")
    return removed

def frame_poses(
    keyframe_of: np.ndarray,
    kf_T_frame: np.ndarray,
    start_T_kf: dict[int, torch.Tensor],
    group_of_kf: dict[int, int],
) -> tuple[np.ndarray, np.ndarray]:
    """Per-frame poses relative to the first contact frame of each frame's group.

    Args:
        keyframe_of: ``(T,)`` int keyframe id of each frame, ``-1`` without contact.
        kf_T_frame: ``(T, 4, 4)`` frame pose in its keyframe (NaN without contact).
        start_T_kf: keyframe id -> ``(4, 4)`` pose in its group's start frame.
        group_of_kf: keyframe id -> group id.

    Returns:
        ``(poses (T, 4, 4), frame_group (T,))``; NaN / -1 for frames without contact.
    """
    t = len(keyframe_of)
    poses = np.full((t, 4, 4), np.nan)
    frame_group = np.full(t, -1, dtype=np.int64)
    has = keyframe_of >= 0
    if not has.any():
        return poses, frame_group
    ids = keyframe_of[has]
    kf_stack = np.stack([start_T_kf[int(i)].numpy() for i in ids])
    start_T_frame = kf_stack @ kf_T_frame[has]
    groups = np.array([group_of_kf[int(i)] for i in ids])
    frame_group[has] = groups
    rel = np.empty_like(start_T_frame)
    for g in np.unique(groups):
        sel = groups == g
        first = np.argmax(sel)  # frames are in video order
        rel[sel] = np.linalg.inv(start_T_frame[first]) @ start_T_frame[sel]
    poses[has] = rel
    return poses, frame_group


def main_group(frame_group: np.ndarray) -> int | None:
    """The group with the most frames with a pose (ties: the one seen first), or
    ``None`` without any. ``(T,)`` int64 -> label. A brief tap before a scan is its own
    small group, so the first contact frame's group is not always the scan."""
    posed = frame_group[frame_group >= 0]
    if len(posed) == 0:
        return None
    labels, first, counts = np.unique(posed, return_index=True, return_counts=True)
    order = np.lexsort((first, -counts))  # most frames, then earliest
    return int(labels[order[0]])


def main_group_poses(poses_by_group: np.ndarray, frame_group: np.ndarray) -> np.ndarray:
    """Keep the :func:`main_group`; NaN elsewhere. ``(T, 4, 4)``."""
    out = np.full_like(poses_by_group, np.nan)
    label = main_group(frame_group)
    if label is not None:
        sel = frame_group == label
        out[sel] = poses_by_group[sel]
    return out


def write_pose_graph_png(path: Path, backend: "BackEnd") -> None:
    """A top view of the back end's largest group (most keyframes): its keyframes,
    coverage keyframes, odometry and loop edges, positions in mm in the group's start
    frame. The back end must hold at least one keyframe."""
    group = dict(backend.group)
    root = max(set(group.values()), key=lambda g: sum(1 for v in group.values() if v == g))
    ids = [k for k in backend.keyframes if group[k] == root]
    row = {k: i for i, k in enumerate(ids)}
    poses = backend.graph.poses(ids).numpy()
    active = set(backend.coverage.active)
    kfs = backend.keyframes
    odo = [(row[k - 1], row[k]) for k in ids
           if k - 1 in row and not kfs[k].new_session and kfs[k - 1].session == kfs[k].session]
    lps = [(row[lp.ref_id], row[lp.tar_id]) for lp in backend.loops if lp.ref_id in row and lp.tar_id in row]
    pose_graph_figure(path, poses[:, :3, 3] * 1000.0, np.array([k in active for k in ids]),
                      np.array(odo, dtype=int).reshape(-1, 2), np.array(lps, dtype=int).reshape(-1, 2),
                      f"pose graph: {len(ids)} keyframes, {len(active & set(ids))} coverage, {len(lps)} loops")


def write_json(path: Path, data: Any) -> None:
    path.write_text(json.dumps(data, indent=2))


FRAME_COLUMNS = ("index", "time_s", "group", "session", "keyframe_id", "is_keyframe", "ccs", "scr", "conditioning")


def write_frames_csv(path: Path, fps: float, frame_group: np.ndarray, keyframe_of: np.ndarray,
                     session_of_kf: dict[int, int], keyframe_indices: set[int], quality: np.ndarray) -> None:
    """``frames.csv``: one row per video index (columns :data:`FRAME_COLUMNS`).

    Args:
        fps: frame rate (``time_s = index / fps``, as ``trajectory_tum.txt``).
        frame_group: ``(T,)`` group of each frame (-1: no pose).
        keyframe_of: ``(T,)`` keyframe each frame's pose is measured from (-1: none).
        session_of_kf: keyframe id -> session id.
        keyframe_indices: video indices of the keyframes.
        quality: ``(T, 3)`` CCS, SCR and conditioning of each frame's accepted
            registration (NaN: a session head, or no contact), written empty when NaN.
    """
    t = len(frame_group)
    session_by_id = np.full(max(session_of_kf, default=-1) + 2, -1, dtype=np.int64)  # last entry: id -1
    session_by_id[list(session_of_kf)] = list(session_of_kf.values())
    session = session_by_id[keyframe_of]
    is_kf = np.zeros(t, dtype=np.int64)
    is_kf[list(keyframe_indices)] = 1
    scores = [["" if v != v else f"{v:.6g}" for v in row] for row in quality.tolist()]  # NaN: empty
    lines = [",".join(FRAME_COLUMNS)] + [
        f"{i},{i / fps:.6f},{frame_group[i]},{session[i]},{keyframe_of[i]},{is_kf[i]}," + ",".join(scores[i])
        for i in range(t)]
    path.write_text("\n".join(lines) + "\n")


class OutputPathError(ValueError):
    """An output folder or file that cannot be written."""


def _writable_parent(path: Path, what: str) -> None:
    """The nearest existing ancestor of ``path`` must be a folder this process can create
    entries in (the missing folders between are created later)."""
    parent = path.absolute().parent
    while not parent.exists():
        parent = parent.parent
    if not parent.is_dir():
        raise OutputPathError(f"{what} {path}: {parent} is a file, not a folder")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise OutputPathError(f"{what} {path}: no permission to write in {parent}")


def check_output_folder(path: str | Path) -> Path:
    """A folder to write into: missing (created later) or an existing, writable folder;
    never an existing file. Returns it as a :class:`Path`."""
    if str(path) == "":
        raise OutputPathError("output folder: empty path")
    path = Path(path)
    if path.exists():
        if not path.is_dir():
            raise OutputPathError(f"output folder {path} is an existing file")
        if not os.access(path, os.W_OK | os.X_OK):
            raise OutputPathError(f"output folder {path}: no permission to write in it")
    else:
        _writable_parent(path, "output folder")
    return path


def check_output_file(path: str | Path) -> Path:
    """A file to write: missing or an existing file (replaced), in a folder that exists or
    can be created; never an existing folder. Returns it as a :class:`Path`."""
    if str(path) == "":
        raise OutputPathError("output file: empty path")
    path = Path(path)
    if path.is_dir():
        raise OutputPathError(f"output file {path} is an existing folder")
    if path.exists() and not os.access(path, os.W_OK):
        raise OutputPathError(f"output file {path}: no permission to write it")
    _writable_parent(path, "output file")
    return path
