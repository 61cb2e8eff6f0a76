"""The full offline pipeline on real GelSight Mini images (../shared calibration presses).

The presses are steel balls on a real gel, decoded by the shipped model: a recorded scan
is assembled from them (background frames, then each press held for a few frames with
the unloaded gel in between) and run like any ``gelsight.avi`` scan. It checks what the
simulator cannot: contact detection and session logic on real colours and real noise.
"""

import csv

import cv2
import numpy as np
import pytest

from tactile_slam.config import Config
from tactile_slam.io.dispatch import open_source
from tactile_slam.io.video import write_video
from tactile_slam.pipeline.offline import OfflinePipeline, RunOptions

HOLD, GAP = 4, 2  # frames per press, unloaded frames after it


@pytest.fixture(scope="module")
def run(mini_data, tmp_path_factory):
    root = mini_data / "calibration"
    rows = list(csv.DictReader(open(root / "catalog.csv")))
    bg = cv2.imread(str(root / "background.png"))
    cfg = Config()
    frames, label = [bg] * cfg.sensor.background_frames, [-1] * cfg.sensor.background_frames
    for i, row in enumerate(rows):
        frames += [cv2.imread(str(root / row["experiment_reldir"] / "gelsight.png"))] * HOLD + [bg] * GAP
        label += [i] * HOLD + [-1] * GAP
    scan = tmp_path_factory.mktemp("real_presses")
    write_video(scan / "gelsight.avi", np.stack(frames), 25.0)
    res = OfflinePipeline(open_source(scan, cfg), cfg, scan / "out", RunOptions(mesh=False, progress=False)).run()
    return res, np.array(label), len(rows)


def test_every_press_is_one_session_and_nothing_else_is_contact(run):
    res, label, n = run
    s = res.stats
    assert s["sessions"] == n and s["contact_frames"] == n * HOLD
    assert s["keyframes"] == 2 * n  # each session's first frame and its flushed tail
    has_pose = np.isfinite(res.poses_by_group[:, 0, 0])
    assert np.array_equal(has_pose, label >= 0)  # every press frame, no unloaded frame


def test_held_press_does_not_move_and_balls_close_no_loop(run):
    """A held press repeats one image: its poses must be the identity. Ball presses are
    spherical caps (rotation about the centre is unobservable), so no loop may form."""
    res, label, n = run
    assert res.stats["loops"] == 0 and res.stats["groups"] == n
    for i in range(n):
        poses = res.poses_by_group[label == i]
        rel = np.linalg.inv(poses[0]) @ poses
        assert np.abs(rel - np.eye(4)).max() < 1e-6, i


def test_main_group_is_the_longest_not_a_first_tap(mini_data, tmp_path):
    """A brief tap before the scan is its own group; ``poses.npy`` follows the group with
    the most posed frames, in the frame of that group's first frame."""
    root = mini_data / "calibration"
    bg = cv2.imread(str(root / "background.png"))
    tap, press = (cv2.imread(str(root / r / "gelsight.png")) for r in ("6.310mm/3", "9.500mm/2"))
    frames = [bg] * 10 + [tap] * 2 + [bg] * 3 + [press] * 6 + [bg] * 2
    write_video(tmp_path / "gelsight.avi", np.stack(frames), 25.0)
    cfg = Config()
    opts = RunOptions(mesh=False, progress=False)
    res = OfflinePipeline(open_source(tmp_path, cfg), cfg, tmp_path / "out", opts).run()
    assert res.stats["sessions"] == 2
    has = np.isfinite(res.poses[:, 0, 0])
    assert has.nonzero()[0].tolist() == list(range(15, 21))  # the press, not the tap
    np.testing.assert_allclose(res.poses[15], np.eye(4), atol=1e-12)
    assert np.isfinite(res.poses_by_group[10:12, 0, 0]).all()  # the tap keeps its own poses
