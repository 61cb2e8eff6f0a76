"""``LoopedSource``: a recording replayed longer than it is keeps the recording's
background and video indices, and numbers later passes on without repeats."""

from __future__ import annotations

import numpy as np
import pytest

from tactile_slam.config import Config
from tactile_slam.geometry.frame import InputError
from tactile_slam.io import Scan, write_video
from tactile_slam.io.frames import RawFrame, SequenceSource
from tactile_slam.io.replay import LoopedSource


@pytest.fixture
def scan(tmp_path, gel_frames):
    """A 48x64 scan: 10 background frames, then 6 data frames (video indices 10-15)."""
    write_video(tmp_path / "scan" / "gelsight.avi", gel_frames(16, (48, 64), seed=5), fps=25)
    config = Config()
    config.sensor.height, config.sensor.width = 48, 64
    config.save(tmp_path / "scan" / "config.yaml")
    return Scan(tmp_path / "scan")


def test_first_pass_is_the_scan_itself(scan):
    """The looped scan had no background (the pipeline took its first frames, in
    contact, instead) and renumbered frames by position (row 0 was video frame 10)."""
    loop = LoopedSource(scan, len(scan))
    np.testing.assert_array_equal(loop.background, scan.background)
    assert loop.background_check == scan.background_check
    for a, b in zip(loop, scan):
        assert (a.index, a.timestamp) == (b.index, b.timestamp)
        np.testing.assert_array_equal(a.bgr, b.bgr)


def test_later_passes_continue_the_numbering(scan):
    loop = LoopedSource(scan, 15)  # two and a half passes over 6 frames
    assert loop.span == 6
    assert [f.index for f in loop] == list(range(10, 25))
    np.testing.assert_allclose([f.timestamp for f in loop], np.arange(10, 25) / 25.0)
    np.testing.assert_array_equal(loop[7].bgr, scan[1].bgr)
    assert loop[-1].index == 24


class Gapped(SequenceSource):
    """Three gradient frames at video indices 2, 5, 6."""

    fps, shape, name = 10.0, (4, 4), "gapped"

    def __len__(self):
        return 3

    def frame(self, position):
        index = (2, 5, 6)[position]
        return RawFrame(index, index / self.fps, gradients=np.full((4, 4, 2), position, np.float32))


def test_a_source_with_gaps_keeps_them_and_never_repeats_an_index():
    loop = LoopedSource(Gapped(), 7)
    assert loop.span == 5 and loop.background is None and loop.background_check is None
    assert [f.index for f in loop] == [2, 5, 6, 7, 10, 11, 12]
    assert [float(f.gradients[0, 0, 0]) for f in loop] == [0, 1, 2, 0, 1, 2, 0]


def test_refuses_empty_or_non_positive_lengths(scan):
    with pytest.raises(InputError, match="cannot loop"):
        LoopedSource(scan, 0)
