import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from tactile_slam.eval.loop_metrics import (gt_loop_pairs, joinable_groups, loop_flags, loop_precision_recall,
                                           overlap_mm2, relative_pose_errors, tilt_twist_deg,
                                           within_tolerance)

S_MM = 0.0634


def poses():
    rng = np.random.default_rng(0)
    out = np.tile(np.eye(4), (60, 1, 1))
    out[:, :3, :3] = Rotation.from_rotvec(rng.normal(0, 0.2, (60, 3))).as_matrix()
    out[:, :3, 3] = rng.normal(0, 0.005, (60, 3))
    return out


def test_precision_recall_hand_computed():
    gt = poses()
    pairs = np.array([[2, 40], [5, 50], [7, 30], [10, 45]])
    rel = np.linalg.inv(gt[pairs[:, 0]]) @ gt[pairs[:, 1]]
    rel[1, 0, 3] += 0.0002  # 0.2 mm: still correct
    rel[2, 1, 3] += 0.0005  # 0.5 mm: wrong
    rel[3, :3, :3] = rel[3, :3, :3] @ Rotation.from_rotvec([0, 0, np.deg2rad(2.0)]).as_matrix()  # 2 deg: wrong
    dt, dr = relative_pose_errors(rel, pairs, gt)
    assert np.allclose(dt, [0, 0.2, 0.5, 0], atol=1e-9) and np.allclose(dr, [0, 0, 0, 2.0], atol=1e-6)
    gt_pairs = np.array([[40, 2], [5, 50], [20, 55]])  # order inside a pair does not matter
    m = loop_precision_recall(pairs, rel, gt, gt_pairs)
    assert m["reported"] == 4 and m["correct"] == 2 and m["precision"] == pytest.approx(0.5)
    assert m["gt_loops"] == 3 and m["found"] == 2 and m["recall"] == pytest.approx(2 / 3)
    empty = loop_precision_recall(np.zeros((0, 2)), np.zeros((0, 4, 4)), gt)
    assert empty["reported"] == 0 and np.isnan(empty["precision"])
    with pytest.raises(ValueError, match="outside"):
        loop_precision_recall(np.array([[0, 99]]), np.eye(4)[None], gt)


def test_loops_without_known_depth_are_scored_across_the_sensor_axis():
    """A loop whose keyframes include one without undeformed gel in view carries that
    keyframe's guessed height zero in its z: scored on x, y and rotation only."""
    gt = poses()
    pairs = np.array([[2, 40], [5, 50]])
    rel = np.linalg.inv(gt[pairs[:, 0]]) @ gt[pairs[:, 1]]
    lateral = np.eye(4)
    lateral[:3, 3] = [3e-4, 4e-4, 7e-4]  # error in frame j: 0.5 mm across the axis, 0.7 mm along it
    rel = rel @ lateral
    dt, _ = relative_pose_errors(rel, pairs, gt, np.array([True, False]))
    np.testing.assert_allclose(dt, [np.sqrt(0.74), 0.5], rtol=1e-9)
    np.testing.assert_allclose(relative_pose_errors(rel, pairs, gt)[0], [np.sqrt(0.74)] * 2, rtol=1e-9)
    rel[:, :3, 3] -= (rel[:, :3, :3] @ np.array([3e-4, 4e-4, 0.0]))  # only the z error is left
    m = loop_precision_recall(pairs, rel, gt, depth_known=np.array([True, False]))
    assert m["correct"] == 1 and m["reported"] == 2
    with pytest.raises(ValueError, match="depth flags"):
        relative_pose_errors(rel, pairs, gt, np.array([True]))


def test_tilt_twist_split_against_quaternions():
    """The tilt is the angle the rotation turns z by; the twist the rotation about z left
    after it (2 atan2(q_z, q_w) of the quaternion), checked against scipy."""
    rng = np.random.default_rng(3)
    rot = Rotation.from_rotvec(rng.normal(0, 0.6, (200, 3)))
    tilt, twist = tilt_twist_deg(rot.as_matrix())
    q = rot.as_quat()  # x, y, z, w
    want_twist = np.degrees(np.abs(np.angle(np.exp(2j * np.arctan2(q[:, 2], q[:, 3])))))
    want_tilt = np.degrees(np.arccos(np.clip(rot.apply([0.0, 0.0, 1.0])[:, 2], -1, 1)))
    np.testing.assert_allclose(tilt, want_tilt, atol=1e-9)
    np.testing.assert_allclose(twist, want_twist, atol=1e-6)
    pure = Rotation.from_euler("zx", [[30.0, 0.0], [0.0, 7.0], [-50.0, 4.0]], degrees=True).as_matrix()
    tilt, twist = tilt_twist_deg(pure)  # R = Rz Rx: a 7 deg or 4 deg swing after a turn about z
    np.testing.assert_allclose(tilt, [0.0, 7.0, 4.0], atol=1e-9)
    np.testing.assert_allclose(twist, [30.0, 0.0, 50.0], atol=1e-9)


def test_within_tolerance_rule():
    """Geodesic rotation without a declared sigma; twist and widened tilt with one; NaN is out."""
    nan = np.nan
    rot = np.array([0.9, 1.1, 3.0, 3.0, 0.5, 1.5, nan, 0.5])
    tilt = np.array([0.9, 1.1, 3.0, 3.0, 0.5, 0.1, 0.0, 0.5])
    twist = np.array([0.1, 0.1, 0.1, 0.1, 0.1, 1.5, 0.0, 0.1])
    trans = np.array([0.1, 0.1, 0.1, 0.1, 0.31, 0.1, 0.1, nan])
    sigma = np.array([nan, nan, nan, 5.44, 5.44, 5.44, nan, 5.44])
    got = within_tolerance(rot, tilt, twist, trans, sigma, 1.0, 0.3)
    assert got.tolist() == [True, False, False, True, False, False, False, False]


def test_loops_with_a_declared_tilt_sigma_are_scored_within_it():
    """A loop from video weighs its tilt by tilt_sigma_deg in the graph: a 3 deg tilt error
    is within a 5.44 deg sigma, not within 1 deg; the rotation about the sensor axis and the
    translation keep the 1 deg / 0.3 mm gate."""
    gt = poses()
    pairs = np.array([[2, 40], [5, 50], [7, 30], [10, 45]])
    rel = np.linalg.inv(gt[pairs[:, 0]]) @ gt[pairs[:, 1]]
    err = Rotation.from_rotvec(np.deg2rad([[3.0, 0, 0], [0, 3.0, 0], [0, 0, 1.5], [0, 6.0, 0]])).as_matrix()
    rel[:, :3, :3] = rel[:, :3, :3] @ err
    loops = [{"depth_known": True, "tilt_sigma_deg": 5.44}] * 4
    known, sigma = loop_flags(loops)
    m = loop_precision_recall(pairs, rel, gt, depth_known=known, tilt_sigma_deg=sigma)
    assert m["reported"] == 4 and m["correct"] == 2 and m["correct_full_pose"] == 0  # twist 1.5, tilt 6 fail
    none = loop_precision_recall(pairs, rel, gt, tilt_sigma_deg=np.full(4, np.nan))
    assert none["correct"] == 0 and none == loop_precision_recall(pairs, rel, gt)
    # a sigma below the gate does not tighten it: a 0.8 deg tilt error passes with sigma 0.1
    rel2 = np.linalg.inv(gt[pairs[:1, 0]]) @ gt[pairs[:1, 1]]
    rel2[0, :3, :3] = rel2[0, :3, :3] @ Rotation.from_rotvec([np.deg2rad(0.8), 0, 0]).as_matrix()
    assert loop_precision_recall(pairs[:1], rel2, gt, tilt_sigma_deg=np.array([0.1]))["correct"] == 1
    assert loop_flags([{}])[0].tolist() == [True] and np.isnan(loop_flags([{"tilt_sigma_deg": None}])[1]).all()
    with pytest.raises(ValueError, match="tilt sigmas"):
        loop_precision_recall(pairs, rel, gt, tilt_sigma_deg=np.ones(3))


def test_overlap_of_shifted_square_patch():
    """A 60x60 px flat patch seen again after the sensor moved 10 px along x: the
    overlap is 50x60 px."""
    h = np.zeros((240, 320))
    c = np.zeros((240, 320), bool)
    c[90:150, 130:190] = True
    j_T_i = np.eye(4)
    j_T_i[0, 3] = -10 * S_MM * 1e-3  # the object moves -10 px in the new sensor frame
    assert overlap_mm2(h, c, h, c, np.eye(4), S_MM) == pytest.approx(3600 * S_MM**2)
    assert overlap_mm2(h, c, h, c, j_T_i, S_MM) == pytest.approx(3000 * S_MM**2)
    far = np.eye(4)
    far[2, 3] = 0.001  # 1 mm apart in depth: not the same surface
    assert overlap_mm2(h, c, h, c, far, S_MM) == 0


def test_gt_loop_pairs():
    t = 60
    obj = np.tile(np.eye(4), (t, 1, 1))
    obj[:, 0, 3] = np.where(np.arange(t) < 30, np.arange(t), 59 - np.arange(t)) * 0.5e-3  # out and back
    h = np.zeros((t, 240, 320))
    c = np.zeros((t, 240, 320), bool)
    c[:, 60:180, 80:240] = True
    pairs = gt_loop_pairs(np.arange(0, t, 5), obj, h, c, S_MM, min_overlap_mm2=40.0, min_gap=25)
    # frames 0 and 55 are 2 mm = 31.5 px apart: (160 - 31.5) x 120 px = 62 mm^2 shared
    assert [0, 55] in pairs.tolist()
    max_shift_px = 160 - 40 / S_MM**2 / 120  # the shift that leaves exactly 40 mm^2
    for i, j in pairs:
        assert j - i >= 25
        assert abs(obj[i, 0, 3] - obj[j, 0, 3]) * 1e3 / S_MM <= max_shift_px


def _disc_keyframes(x_mm: list[float], radius_mm: float = 2.0):
    """Flat touches: a contact disc of ``radius_mm`` at the image centre, sensors at
    ``x_mm`` along the object's x axis. Returns ``(object_T_sensor, height, contact)``."""
    k = len(x_mm)
    obj = np.tile(np.eye(4), (k, 1, 1))
    obj[:, 0, 3] = np.asarray(x_mm) * 1e-3
    r, c = np.mgrid[:240, :320]
    disc = np.hypot((c - 159.5) * S_MM, (r - 119.5) * S_MM) <= radius_mm
    return obj, np.zeros((k, 240, 320)), np.repeat(disc[None], k, axis=0)


def test_joinable_groups_join_sessions_that_share_surface():
    """Sessions 0 (keyframes 0, 1) and 1 (keyframe 2) share the lens of two 2 mm discs
    1 mm apart (2 r^2 acos(d / 2r) - d/2 sqrt(4 r^2 - d^2) = 8.61 mm^2); session 2 (keyframe 3)
    is 10 mm away and shares nothing; session 3 (keyframe 4) lies on keyframe 3."""
    obj, h, c = _disc_keyframes([0.0, 4.0, 5.0, 20.0, 20.0])
    lens = 8 * np.arccos(0.25) - 0.5 * np.sqrt(15)
    assert overlap_mm2(h[1], c[1], h[2], c[2], np.linalg.inv(obj[2]) @ obj[1], S_MM) == pytest.approx(lens, rel=0.02)
    label = joinable_groups(np.array([0, 0, 1, 2, 3]), obj, h, c, S_MM, min_overlap_mm2=5.0)
    assert label.shape == (5,) and label.dtype == np.int64
    assert label[0] == label[1] == label[2] and label[3] == label[4] and label[0] != label[3]
    # asking for more than the lens (but less than a whole disc, 12.57 mm^2) parts sessions 0 and 1
    part = joinable_groups(np.array([0, 0, 1, 2, 3]), obj, h, c, S_MM, min_overlap_mm2=10.0)
    assert part[0] == part[1] and part[3] == part[4] and len({part[0], part[2], part[3]}) == 3
    # keyframes of one session are one group however far apart
    assert len(set(joinable_groups(np.zeros(5), obj, h, c, S_MM).tolist())) == 1
    with pytest.raises(ValueError, match="one session per keyframe"):
        joinable_groups(np.zeros(4), obj, h, c, S_MM)
    assert joinable_groups(np.zeros(0), obj[:0], h[:0], c[:0], S_MM).shape == (0,)
