"""Trajectories: TUM text files and re-expression relative to a reference frame.

Poses are ``(T, 4, 4)`` float64 homogeneous matrices in metres; a row of NaN marks a
frame without an estimate. TUM files list ``timestamp tx ty tz qx qy qz qw`` per line
(metres, Hamilton quaternion, scalar last) for the frames that have a pose.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation


class TrajectoryError(ValueError):
    """A trajectory file or array is malformed."""


RIGID_TOL = 1e-4
"""Largest deviation of ``R R^T`` from the identity, and of the bottom row from
``0 0 0 1``, that a pose may have."""


def check_trajectory(poses: np.ndarray, where: str = "trajectory") -> np.ndarray:
    """``(T, 4, 4)`` float64 copy of ``poses``; NaN rows allowed, Inf and non-rigid not.

    A frame with a pose is rigid when its rotation is orthonormal and has determinant +1
    (no reflection) and its bottom row is ``0 0 0 1``, each within :data:`RIGID_TOL`.

    Raises:
        TrajectoryError: naming ``where`` and, for a non-rigid pose, the first such
            frame (its index in ``poses``: the video frame of a run's ``poses.npy``).
    """
    arr = np.asarray(poses)
    if arr.dtype.kind not in "biuf":
        raise TrajectoryError(f"{where}: poses must be numbers, got dtype {arr.dtype}")
    poses = np.array(arr, dtype=np.float64)
    if poses.ndim != 3 or poses.shape[1:] != (4, 4):
        raise TrajectoryError(f"{where}: poses must be (T, 4, 4), got {poses.shape}")
    if len(poses) == 0:
        raise TrajectoryError(f"{where}: empty trajectory")
    if np.isinf(poses).any():
        raise TrajectoryError(f"{where}: poses contain Inf")
    frames = np.flatnonzero(valid_mask(poses))
    rot, bottom = poses[frames, :3, :3], poses[frames, 3]
    ortho = np.abs(rot @ rot.transpose(0, 2, 1) - np.eye(3)).max(axis=(1, 2), initial=0.0)
    det = np.linalg.det(rot)
    off = np.abs(bottom - [0.0, 0.0, 0.0, 1.0]).max(axis=1, initial=0.0)
    for bad, what in ((ortho > RIGID_TOL, lambda k: f"rotation is not orthonormal (|R R^T - I| = {ortho[k]:.3g})"),
                      (det < 0, lambda k: f"rotation has determinant {det[k]:.3g}, a reflection, not +1"),
                      (off > RIGID_TOL, lambda k: f"bottom row is {bottom[k].tolist()}, not [0, 0, 0, 1]")):
        if bad.any():
            k = int(np.argmax(bad))
            raise TrajectoryError(f"{where}: frame {frames[k]} is not a rigid pose: {what(k)} "
                                  f"({int(bad.sum())} of the {len(frames)} frames with a pose fail this check)")
    return poses


def read_poses(path: str | Path) -> np.ndarray:
    """A ``.npy`` file of poses -> :func:`check_trajectory`'s ``(T, 4, 4)`` float64.

    Raises:
        TrajectoryError: naming ``path``: missing, not a ``.npy`` file, unreadable (e.g.
            pickled objects) or not a trajectory of rigid poses.
    """
    path = Path(path)
    if not path.is_file():
        raise TrajectoryError(f"pose file not found: {path}")
    with path.open("rb") as f:
        if f.read(6) != b"\x93NUMPY":
            raise TrajectoryError(f"{path} is not a NumPy .npy file (it does not start with the .npy header)")
    try:
        poses = np.load(path, allow_pickle=False)
    except (ValueError, OSError, EOFError) as exc:
        raise TrajectoryError(f"cannot read {path}: {exc}") from exc
    return check_trajectory(poses, str(path))


def valid_mask(poses: np.ndarray) -> np.ndarray:
    """``(T,)`` bool: frames whose pose is fully finite."""
    return np.isfinite(np.asarray(poses).reshape(len(poses), -1)).all(axis=1)


def relative_to(poses: np.ndarray, index: int = 0) -> np.ndarray:
    """Re-express ``world_T_i`` as ``ref_T_i = inv(world_T_ref) @ world_T_i`` with
    ``ref = index``. ``(T, 4, 4)`` -> ``(T, 4, 4)``; NaN rows stay NaN."""
    poses = np.asarray(poses, dtype=np.float64)
    ref = poses[index]
    if not np.isfinite(ref).all():
        raise TrajectoryError(f"reference frame {index} has no pose")
    return np.linalg.inv(ref) @ poses


def write_tum(path: str | Path, timestamps: np.ndarray, poses: np.ndarray) -> Path:
    """Write the frames that have a pose as TUM lines. ``timestamps`` ``(T,)`` seconds."""
    poses = check_trajectory(poses)
    timestamps = np.asarray(timestamps, dtype=np.float64)
    if timestamps.shape != (len(poses),):
        raise TrajectoryError(f"timestamps {timestamps.shape} do not match {len(poses)} poses")
    ok = valid_mask(poses)
    q = Rotation.from_matrix(poses[ok, :3, :3]).as_quat() if ok.any() else np.zeros((0, 4))
    rows = np.column_stack([timestamps[ok], poses[ok, :3, 3], q])
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savetxt(path, rows, fmt="%.9f", header="timestamp tx ty tz qx qy qz qw")
    return path


def read_tum(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """Read a TUM file -> ``(timestamps (T,), poses (T, 4, 4))``."""
    path = Path(path)
    if not path.is_file():
        raise TrajectoryError(f"trajectory file not found: {path}")
    try:
        rows = np.loadtxt(path, comments="#", ndmin=2)
    except ValueError as exc:
        raise TrajectoryError(f"{path}: not a TUM trajectory: {exc}") from exc
    if rows.size == 0:
        raise TrajectoryError(f"{path}: no poses")
    if rows.shape[1] != 8:
        raise TrajectoryError(f"{path}: TUM lines have 8 columns, found {rows.shape[1]}")
    if not np.isfinite(rows).all():
        raise TrajectoryError(f"{path}: non-finite values")
    norm = np.linalg.norm(rows[:, 4:], axis=1)
    if (np.abs(norm - 1) > 1e-3).any():
        raise TrajectoryError(f"{path}: quaternions are not unit length")
    poses = np.tile(np.eye(4), (len(rows), 1, 1))
    poses[:, :3, :3] = Rotation.from_quat(rows[:, 4:]).as_matrix()
    poses[:, :3, 3] = rows[:, 1:4]
    return rows[:, 0], poses
