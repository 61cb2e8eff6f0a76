"""Trajectory I/O and tracking metrics against hand-computed values."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from tactile_slam.eval.tracking_metrics import (ate, frame_steps, geodesic_deg, motion_range, per_axis_errors, per_axis_mae,
                                                pose_vector, rpe, tracking_report, travel_pairs, umeyama)
from tactile_slam.eval.trajectory import (TrajectoryError, check_trajectory, read_poses, read_tum, relative_to,
                                         valid_mask, write_tum)


def rx(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


def ry(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def rz(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


def pose(r=np.eye(3), t=(0, 0, 0)):
    p = np.eye(4)
    p[:3, :3], p[:3, 3] = r, t
    return p


def line(n, step_m=1e-3):
    """Straight-line trajectory along x, ``step_m`` per frame."""
    return np.stack([pose(t=(k * step_m, 0, 0)) for k in range(n)])


def test_pose_vector_is_extrinsic_zxy_reordered():
    """R = Ry(b) Rx(a) Rz(c) (extrinsic z, then x, then y) -> (a, b, c) in degrees."""
    a, b, c = np.deg2rad([10.0, -20.0, 30.0])
    v = pose_vector(pose(ry(b) @ rx(a) @ rz(c), (0.001, -0.002, 0.0005))[None])[0]
    assert np.allclose(v, [1.0, -2.0, 0.5, 10.0, -20.0, 30.0])


def test_per_axis_mae_hand_computed():
    gt = line(5)
    est = gt.copy()
    est[0, 0, 3] += 0.01  # frame 0 is skipped
    est[1:, 1, 3] += np.array([0.1, 0.2, 0.3, 0.4]) * 1e-3
    est[2, :3, :3] = rz(np.deg2rad(2.0))
    m = per_axis_mae(est, gt)
    assert m["x_mm"] == pytest.approx(0.0) and m["y_mm"] == pytest.approx(0.25)
    assert m["rz_deg"] == pytest.approx(0.5) and m["rx_deg"] == pytest.approx(0.0)
    assert m["n_frames"] == 4


def test_no_angle_wrapping_and_nan_frames():
    gt = np.stack([pose(), pose(rz(np.deg2rad(179.0))), pose()])
    est = np.stack([pose(), pose(rz(np.deg2rad(-179.0))), np.full((4, 4), np.nan)])
    err = per_axis_errors(est, gt)
    assert err[1, 5] == pytest.approx(358.0)  # as NormalFlow's scripts: no wrapping
    assert np.isnan(err[2]).all()
    m = per_axis_mae(est, gt)
    assert m["n_frames"] == 1 and m["rz_deg"] == pytest.approx(358.0)
    assert geodesic_deg(est[1, :3, :3], gt[1, :3, :3]) == pytest.approx(2.0)


def test_geodesic_and_umeyama():
    axis = np.array([1.0, 2.0, -0.5]) / np.linalg.norm([1.0, 2.0, -0.5])
    r = Rotation.from_rotvec(axis * np.deg2rad(30)).as_matrix()
    assert geodesic_deg(np.eye(3), r) == pytest.approx(30.0)
    rng = np.random.default_rng(0)
    src = rng.normal(size=(20, 3))
    t = pose(r, (0.1, -0.2, 0.3))
    dst = src @ r.T + t[:3, 3]
    assert np.allclose(umeyama(src, dst), t)


def test_ate_unaligned_and_aligned():
    gt = line(10)
    est = gt.copy()
    est[:, 2, 3] += 0.001  # constant 1 mm offset
    assert ate(est, gt)["trans_rmse_mm"] == pytest.approx(1.0)
    assert ate(est, gt, align=True)["trans_rmse_mm"] == pytest.approx(0.0, abs=1e-9)
    est[:, :3, :3] = rx(np.deg2rad(1.0))
    assert ate(est, gt)["rot_rms_deg"] == pytest.approx(1.0)
    # two usable frames: unaligned ATE is defined, the alignment is not (NaN, not an error)
    est[2:] = np.nan
    assert ate(est, gt)["n_frames"] == 2 and np.isfinite(ate(est, gt)["trans_rmse_mm"])
    two = ate(est, gt, align=True)
    assert two["n_frames"] == 2 and np.isnan(two["trans_rmse_mm"]) and np.isnan(two["rot_rms_deg"])


def test_rpe_frames_and_travel():
    gt = line(11)
    drift = line(11, 1.1e-3)  # 0.1 mm too far per frame
    assert rpe(drift, gt, 1)["trans_rmse_mm"] == pytest.approx(0.1)
    assert rpe(drift, gt, 5)["trans_rmse_mm"] == pytest.approx(0.5)
    i, j = travel_pairs(gt, 3.0)
    assert np.array_equal(j - i, np.full(len(i), 3)) and len(i) == 8
    r = rpe(drift, gt, None, 3.0)
    assert r["trans_rmse_mm"] == pytest.approx(0.3) and r["n_pairs"] == 8
    with pytest.raises(ValueError):
        rpe(drift, gt, 1, 3.0)


def test_motion_range_and_report():
    gt = np.stack([pose(rz(np.deg2rad(a)), (0, 0.001 * k, 0)) for k, a in enumerate([0, 10, 5, 15])])
    m = motion_range(gt)
    assert m["rz_deg"] == pytest.approx(25.0) and m["y_mm"] == pytest.approx(3.0) and m["x_mm"] == 0
    est = gt.copy()
    est[3] = np.nan
    rep = tracking_report(est, gt)
    assert rep["estimated_fraction"] == pytest.approx(0.75)
    assert rep["per_axis_mae"]["n_frames"] == 2


def test_frame_steps():
    gt = np.stack([pose(rz(np.deg2rad(a)), (0, 0.001 * k, 0)) for k, a in enumerate([0, 10, 5, 15])])
    deg, mm = frame_steps(gt)
    np.testing.assert_allclose(deg, [10.0, 5.0, 10.0], atol=1e-9)
    np.testing.assert_allclose(mm, [1.0, 1.0, 1.0], atol=1e-9)  # rotations about the origin keep |t| steps
    deg, mm = frame_steps(gt, np.array([True, True, False, True]))
    assert deg[0] == pytest.approx(10.0) and np.isnan(deg[1:]).all() and np.isnan(mm[1:]).all()
    gt[1] = np.nan
    assert np.isnan(frame_steps(gt)[0][:2]).all()


def test_relative_to_and_validation():
    p = np.stack([pose(rz(0.3), (1, 2, 3)), pose(rx(0.2), (0, 1, 0))])
    rel = relative_to(p, 0)
    assert np.allclose(rel[0], np.eye(4)) and np.allclose(p[0] @ rel[1], p[1])
    with pytest.raises(TrajectoryError, match="no pose"):
        relative_to(np.full((2, 4, 4), np.nan), 0)
    with pytest.raises(TrajectoryError, match="differ"):
        per_axis_mae(line(3), line(4))
    with pytest.raises(TrajectoryError, match="orthonormal"):
        per_axis_mae(line(3) * 2, line(3))
    with pytest.raises(TrajectoryError, match="ground truth"):
        per_axis_mae(line(3), np.full((3, 4, 4), np.nan))


def test_tum_roundtrip(tmp_path):
    p = np.stack([pose(Rotation.from_rotvec([0.1 * k, -0.2, 0.05]).as_matrix(), (k * 1e-3, 0.002, -1e-4))
                  for k in range(4)])
    p[2] = np.nan
    path = write_tum(tmp_path / "t.txt", np.arange(4) / 25.0, p)
    ts, q = read_tum(path)
    assert np.allclose(ts, [0, 0.04, 0.12])
    assert np.allclose(q, p[valid_mask(p)], atol=1e-8)
    (tmp_path / "bad.txt").write_text("0 1 2 3\n")
    with pytest.raises(TrajectoryError, match="8 columns"):
        read_tum(tmp_path / "bad.txt")
    (tmp_path / "q.txt").write_text("0 0 0 0 0 0 0 2\n")
    with pytest.raises(TrajectoryError, match="unit"):
        read_tum(tmp_path / "q.txt")
    with pytest.raises(TrajectoryError, match="not found"):
        read_tum(tmp_path / "none.txt")


def test_check_trajectory_names_the_first_non_rigid_frame():
    """The frame is the row of ``poses`` (NaN rows counted), not an index among the rows
    with a pose; rounding within the tolerance is accepted."""
    p = line(8)
    p[:3] = np.nan
    p[6, :3, :3] = np.diag([1.0, 1.0, -1.0])  # a reflection
    with pytest.raises(TrajectoryError, match=r"^run: frame 6 is not a rigid pose: rotation has determinant -1"):
        check_trajectory(p, "run")
    p[6, :3, :3] = np.eye(3)
    p[4, 3] = [0, 0, 1e-3, 1]
    p[7, 3] = [0, 0, 0, 2]
    with pytest.raises(TrajectoryError, match=r"frame 4 .*bottom row is \[0.0, 0.0, 0.001, 1.0\].*2 of the 5 frames"):
        check_trajectory(p)
    p[4, 3] = p[7, 3] = [0, 0, 0, 1 + 1e-7]
    p[5, :3, :3] = rz(0.1) + 1e-7
    assert np.array_equal(check_trajectory(p), p, equal_nan=True)
    with pytest.raises(TrajectoryError, match="dtype <U1"):
        check_trajectory(np.full((2, 4, 4), "a"))


def test_read_poses_names_the_file(tmp_path):
    np.save(tmp_path / "ok.npy", line(3).astype(np.float32))
    assert read_poses(tmp_path / "ok.npy").dtype == np.float64
    (tmp_path / "text.npy").write_text("0 0 0")
    with pytest.raises(TrajectoryError, match=r"text\.npy is not a NumPy \.npy file"):
        read_poses(tmp_path / "text.npy")
    with pytest.raises(TrajectoryError, match="not found"):
        read_poses(tmp_path / "none.npy")


def test_motion_range_skips_lifts_and_missing_poses_and_unwraps_angles():
    """Summed over the lifts between touches and over the +-180 deg Euler wrap, a seed
    scan's ry came to 646 deg over 140 frames in contact."""
    angles = [0, 10, 5, 100, 170, -175, -170]  # deg about z; 170 -> -175 is a 15 deg turn
    gt = np.stack([pose(rz(np.deg2rad(a)), (0, 0.001 * k, 0)) for k, a in enumerate(angles)])
    m = motion_range(gt[4:])
    assert m["rz_deg"] == pytest.approx(20.0) and m["y_mm"] == pytest.approx(2.0)
    touches = np.array([True, True, True, False, True, True, True])  # frame 3 lifted
    m = motion_range(gt, touches)
    assert m["rz_deg"] == pytest.approx(15.0 + 20.0) and m["y_mm"] == pytest.approx(4.0)
    gt[5] = np.nan  # no pose: the steps either side of it are not known
    assert motion_range(gt, touches)["rz_deg"] == pytest.approx(15.0)
    with pytest.raises(TrajectoryError, match="frames"):
        motion_range(gt, touches[:-1])
