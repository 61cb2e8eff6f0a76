import numpy as np
import pytest
import yaml

import tactile_slam.io.camera as camera_module
from tactile_slam.cli.main import main
from tactile_slam.io import Scan, VideoSource, crop_raw, write_video


@pytest.fixture
def small_config(tmp_path):
    path = tmp_path / "small.yaml"
    path.write_text(yaml.safe_dump({"sensor": {"height": 48, "width": 64}}))
    return path


def test_record_from_video(tmp_path, gel_frames, small_config, capsys):
    frames = gel_frames(20, (48, 64), seed=1)
    write_video(tmp_path / "in.avi", frames, fps=25)
    out = tmp_path / "scan"
    assert main(["record", str(tmp_path / "in.avi"), "--out", str(out), "--config", str(small_config),
                 "--frames", "15"]) == 0
    assert np.array_equal(np.stack([f.bgr for f in VideoSource(out / "gelsight.avi")]), frames[:15])
    scan = Scan(out)  # the written config.yaml describes the recording
    assert scan.config.sensor.shape == (48, 64) and len(scan) == 5
    assert "15 frames" in capsys.readouterr().out


def test_record_seconds_limit(tmp_path, gel_frames, small_config):
    write_video(tmp_path / "in.avi", gel_frames(30, (48, 64)), fps=10)
    out = tmp_path / "scan"
    main(["record", str(tmp_path / "in.avi"), "--out", str(out), "--config", str(small_config), "--seconds", "1.5"])
    assert len(VideoSource(out / "gelsight.avi")) == 15


def test_record_warns_about_touched_background(tmp_path, gel_frames, press, small_config, capsys):
    frames = press(gel_frames(14, (48, 64), noise=1.0), 3, (24, 30), 10, 30)
    write_video(tmp_path / "in.avi", frames, fps=25)
    main(["record", str(tmp_path / "in.avi"), "--out", str(tmp_path / "scan"), "--config", str(small_config)])
    assert "background frames" in capsys.readouterr().out


def test_record_too_short_is_reported(tmp_path, gel_frames, small_config, capsys):
    write_video(tmp_path / "in.avi", gel_frames(4, (48, 64)), fps=25)
    main(["record", str(tmp_path / "in.avi"), "--out", str(tmp_path / "scan"), "--config", str(small_config)])
    assert "fewer than the 10-frame background window" in capsys.readouterr().out


def test_record_from_fake_camera(tmp_path, monkeypatch, capsys):
    raws = [np.random.default_rng(i).integers(0, 256, (480, 640, 3), dtype=np.uint8) for i in range(12)]

    class Fake:
        def __init__(self):
            self.reads = 0

        def isOpened(self):
            return True

        def set(self, prop, value):
            return True

        def read(self):
            if self.reads == len(raws):
                return False, None  # unplugged: the recording so far is kept
            self.reads += 1
            return True, raws[self.reads - 1]

        def release(self):
            pass

    monkeypatch.setattr(camera_module, "open_cv_capture", lambda index: Fake())
    out = tmp_path / "scan"
    assert main(["record", "camera:0", "--out", str(out), "--config", "digit"]) == 2
    assert "read failed on camera 0 after 12 frames" in capsys.readouterr().err
    got = np.stack([f.bgr for f in VideoSource(out / "gelsight.avi")])
    assert np.array_equal(got, np.stack([crop_raw(r, (240, 320)) for r in raws]))
    assert Scan(out).config.sensor.mm_per_px == 0.0405  # the DIGIT config went with it


def test_record_refuses_to_overwrite(tmp_path, gel_frames, small_config):
    (tmp_path / "scan").mkdir()
    (tmp_path / "scan" / "gelsight.avi").write_bytes(b"x")
    write_video(tmp_path / "in.avi", gel_frames(12, (48, 64)), fps=25)
    assert main(["record", str(tmp_path / "in.avi"), "--out", str(tmp_path / "scan"),
                 "--config", str(small_config)]) == 2
