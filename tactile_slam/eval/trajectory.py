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


def check_trajectory(poses: np.ndarray, where: str = "trajectory") -> np.ndarray:
    """``(T, 4, 4)`` float64 copy of ``poses``; NaN rows allowed, Inf and non-rigid not."""
    poses = np.array(poses, dtype=np.float64)
    if poses.ndim != 3 or poses.shape[1:] != (4, 4):
        raise TrajectoryError(f"{where}: poses must be (T, 4, 4), got {poses.shape}")
    if len(poses) == 0:
        raise TrajectoryError(f"{where}: empty trajectory")
    valid = valid_mask(poses)
    if np.isinf(poses).any():
        raise TrajectoryError(f"{where}: poses contain Inf")
    rot = poses[valid, :3, :3]
    if len(rot) and np.abs(rot @ rot.transpose(0, 2, 1) - np.eye(3)).max() > 1e-4:
        raise TrajectoryError(f"{where}: rotations are not orthonormal")
    return poses


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
