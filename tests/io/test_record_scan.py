"""``tactile-slam record`` from a recorded-scan folder (a copy that runs like the original)
and the checks of its ``--seconds`` option."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from tactile_slam.cli.main import main
from tactile_slam.config import Config
from tactile_slam.io import Scan, VideoSource, write_video


@pytest.fixture
def scan_folder(tmp_path, gel_frames, press):
    """A 48x64 scan of 24 frames (a press from frame 10 on) with its own config.yaml,
    whose mm_per_px differs from the default preset's."""
    folder = tmp_path / "scan"
    frames = gel_frames(24, (48, 64), seed=2)
    for i in range(10, 24):
        frames = press(frames, i, (24, 30), 10, 30)
    write_video(folder / "gelsight.avi", frames, fps=25)
    config = Config()
    config.sensor.height, config.sensor.width, config.sensor.mm_per_px = 48, 64, 0.07
    config.save(folder / "config.yaml")
    return folder


@pytest.fixture
def small_config_path(tmp_path):
    path = tmp_path / "small.yaml"
    path.write_text("sensor:\n  height: 48\n  width: 64\n")
    return path


def video(folder):
    return np.stack([f.bgr for f in VideoSource(folder / "gelsight.avi")])


def assert_same_scan(a: Scan, b: Scan):
    assert b.config == a.config
    assert b.start == a.start
    np.testing.assert_array_equal(b.background, a.background)
    assert [f.index for f in b] == [f.index for f in a]
    np.testing.assert_array_equal(np.stack([f.bgr for f in b]), np.stack([f.bgr for f in a]))


def test_record_a_scan_keeps_its_background_window_and_config(scan_folder, tmp_path):
    """Iterating a scan starts after its background window, so recording it dropped
    frames 0-9 (the copy's window was the press), and the copy was written with the
    default preset instead of the scan's config.yaml."""
    out = tmp_path / "copy"
    assert main(["record", str(scan_folder), "--out", str(out)]) == 0
    np.testing.assert_array_equal(video(out), video(scan_folder))
    original, copy = Scan(scan_folder), Scan(out)
    assert copy.config.sensor.mm_per_px == 0.07
    assert [f.index for f in copy][:1] == [10]
    assert_same_scan(original, copy)


def test_record_a_scan_keeps_its_background_png(scan_folder, tmp_path):
    background = np.stack([f.bgr for f in VideoSource(scan_folder / "gelsight.avi")][:10]).mean(axis=0)
    cv2.imwrite(str(scan_folder / "background.png"), np.round(background).astype(np.uint8))
    out = tmp_path / "copy"
    assert main(["record", str(scan_folder), "--out", str(out)]) == 0
    assert (out / "background.png").read_bytes() == (scan_folder / "background.png").read_bytes()
    copy = Scan(out)
    assert copy.start == 0  # every frame is data, as in the original
    assert_same_scan(Scan(scan_folder), copy)


def test_record_a_scan_with_another_config(scan_folder, tmp_path, small_config_path):
    """``--config`` still wins over the scan's own config.yaml."""
    out = tmp_path / "copy"
    assert main(["record", str(scan_folder), "--out", str(out), "--config", str(small_config_path),
                 "--frames", "15"]) == 0
    assert Scan(out).config.sensor.mm_per_px == Config().sensor.mm_per_px
    np.testing.assert_array_equal(video(out), video(scan_folder)[:15])  # the window counts in --frames


@pytest.mark.parametrize("seconds", ["nan", "inf", "-inf", "0", "-1", "abc"])
def test_record_seconds_must_be_finite_and_positive(scan_folder, tmp_path, capsys, seconds):
    """``nan`` recorded everything, 0 and -1 failed with "no frames to write" after the
    folder and its config.yaml were made: all are now refused while parsing."""
    out = tmp_path / "copy"
    with pytest.raises(SystemExit) as exc:
        main(["record", str(scan_folder), "--out", str(out), f"--seconds={seconds}"])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert "argument --seconds" in err and seconds in err
    assert not out.exists()


def test_record_seconds_accepts_a_fraction(scan_folder, tmp_path):
    out = tmp_path / "copy"
    assert main(["record", str(scan_folder), "--out", str(out), "--seconds", "0.5"]) == 0
    assert len(VideoSource(out / "gelsight.avi")) == 13  # 25 fps: frames 0-12 start before 0.5 s
