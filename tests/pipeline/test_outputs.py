"""Choosing the main group of a run (the frame of poses.npy), and the output folder's check."""

import numpy as np
import pytest

from tactile_slam.config import Config
from tactile_slam.pipeline.offline import OfflinePipeline
from tactile_slam.pipeline.online import OnlinePipeline
from tactile_slam.pipeline.outputs import OutputPathError, main_group, main_group_poses


def test_most_frames_wins_ties_go_to_the_earliest():
    assert main_group(np.array([-1, -1])) is None
    assert main_group(np.array([-1, 4, 4, -1, 7, 7, 7, -1])) == 7  # a 2-frame tap, then the scan
    assert main_group(np.array([5, 5, -1, 2, 2])) == 5  # a tie: the group seen first
    assert main_group(np.array([3, 9, 9, 3, 3])) == 3  # frames of a group need not be contiguous


def test_main_group_poses_keeps_only_that_group():
    groups = np.array([-1, 4, 4, 7, 7, 7])
    by_group = np.tile(np.eye(4), (6, 1, 1))
    by_group[0] = np.nan
    out = main_group_poses(by_group, groups)
    assert np.isnan(out[:3]).all() and np.array_equal(out[3:], by_group[3:])
    assert np.isnan(main_group_poses(by_group[:1], groups[:1])).all()


def test_a_pipeline_checks_its_output_folder_before_reading_a_frame(tmp_path):
    """The offline pipeline wrote its folder only at the end of a run: an ``out_dir``
    that is a file (or lies under one) lost the whole run. It is now refused when the
    pipeline is built, before the source is read."""
    class Untouchable:
        def __iter__(self):
            raise AssertionError("the source was read")

    taken = tmp_path / "taken"
    taken.write_text("x")
    for pipeline in (OfflinePipeline, OnlinePipeline):
        with pytest.raises(OutputPathError, match="is an existing file"):
            pipeline(Untouchable(), Config(), taken)
        with pytest.raises(OutputPathError, match="is a file, not a folder"):
            pipeline(Untouchable(), Config(), taken / "run")
    assert OfflinePipeline(Untouchable(), Config(), tmp_path / "new").out_dir == tmp_path / "new"
    assert not (tmp_path / "new").exists()  # created when the first result is written
