import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from tactile_slam.eval.loop_metrics import gt_loop_pairs, loop_precision_recall, overlap_mm2, relative_pose_errors

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
