import cv2
import numpy as np
import pytest
import yaml

import tactile_slam.io.camera as camera_module
from tactile_slam.config import Config, digit
from tactile_slam.io import (
    CameraSource,
    GradientSequence,
    ImageFolder,
    InputError,
    Scan,
    VideoSource,
    open_source,
    write_video,
)


@pytest.fixture
def small_config():
    cfg = Config()
    cfg.sensor.height, cfg.sensor.width, cfg.sensor.fps = 48, 64, 30.0
    return cfg


class TestOpenSource:
    def test_scan_folder_uses_its_config(self, tmp_path, gel_frames):
        folder = tmp_path / "scan"
        folder.mkdir()
        write_video(folder / "gelsight.avi", gel_frames(12, (48, 64)), fps=25)
        (folder / "config.yaml").write_text(yaml.safe_dump({"device_config": {"imgh": 48, "imgw": 64, "ppmm": 0.05}}))
        src = open_source(folder)
        assert isinstance(src, Scan) and len(src) == 2 and src.config.sensor.mm_per_px == 0.05

    def test_video_file(self, tmp_path, frames, small_config):
        write_video(tmp_path / "clip.avi", frames, fps=25)
        src = open_source(tmp_path / "clip.avi", small_config)
        assert isinstance(src, VideoSource) and len(src) == 14 and src.fps == 25
        with pytest.raises(InputError, match="working size is 320x240"):
            open_source(str(tmp_path / "clip.avi"))
        assert open_source(tmp_path / "clip.avi", resize=True).shape == (240, 320)

    def test_image_folder(self, tmp_path, frames, small_config):
        (tmp_path / "imgs").mkdir()
        for i in range(3):
            cv2.imwrite(str(tmp_path / "imgs" / f"{i}.png"), frames[i])
        src = open_source(tmp_path / "imgs", small_config)
        assert isinstance(src, ImageFolder) and len(src) == 3 and src.fps == 30.0

    def test_gradient_folder_and_files(self, tmp_path, small_config):
        g = np.zeros((3, 48, 64, 2), np.float32)
        c = np.zeros((3, 48, 64), bool)
        (tmp_path / "trial").mkdir()
        np.save(tmp_path / "trial" / "gradient_maps.npy", g)
        np.save(tmp_path / "trial" / "contact_masks.npy", c)
        np.savez(tmp_path / "gt_gradients.npz", gradients=g, contact=c)
        for spec in (tmp_path / "trial", tmp_path / "trial" / "gradient_maps.npy", tmp_path / "gt_gradients.npz"):
            src = open_source(spec, small_config)
            assert isinstance(src, GradientSequence) and len(src) == 3 and src.fps == 30.0

    def test_gradient_level_episode_folder(self, tmp_path, small_config):
        """A simulated gradient-level episode (no video) opens through its gt_gradients.npz;
        an image-level one (video and gt_gradients.npz) reads the video."""
        g = np.random.default_rng(0).normal(0, 0.1, (3, 48, 64, 2)).astype(np.float16)
        c = np.zeros((3, 48, 64), bool)
        c[1, 10:20, 10:30] = True
        ep = tmp_path / "ep"
        ep.mkdir()
        np.savez(ep / "gt_gradients.npz", gradients=g, contact=c)
        (ep / "meta.yaml").write_text("level: gradients\n")
        src = open_source(ep, small_config)
        assert isinstance(src, GradientSequence) and len(src) == 3
        frame = next(iter(src))
        assert np.allclose(np.asarray(frame.gradients), g[0].astype(np.float32))
        with pytest.raises(InputError, match="no gt_gradients.npz"):
            open_source(tmp_path, small_config)  # holds only the episode folder

    @pytest.mark.parametrize("bad, message", [("nan", "frame 1 contain NaN"), ("shape", "working size is 64x48"),
                                              ("empty", "empty")])
    def test_bad_gradient_level_episode(self, tmp_path, small_config, bad, message):
        """The episode's gradient record is checked like any gradient sequence."""
        g = np.zeros((0 if bad == "empty" else 2, 48, 64 if bad != "shape" else 63, 2), np.float32)
        if bad == "nan":
            g[1, 5, 5, 0] = np.nan
        c = np.zeros(g.shape[:3], bool)
        ep = tmp_path / "ep"
        ep.mkdir()
        np.savez(ep / "gt_gradients.npz", gradients=g, contact=c)
        with pytest.raises(InputError, match=message):
            src = open_source(ep, small_config)
            for _ in src:
                pass

    def test_camera(self, monkeypatch):
        class Fake:
            def __init__(self):
                self.props = {}

            def isOpened(self):
                return True

            def set(self, prop, value):
                self.props[prop] = value

            def read(self):
                return True, np.zeros((480, 640, 3), np.uint8)

            def release(self):
                pass

        fakes = {}
        monkeypatch.setattr(camera_module, "open_cv_capture", lambda i: fakes.setdefault(i, Fake()))
        src = open_source("camera:1", digit())
        assert isinstance(src, CameraSource) and src.device_index == 1 and src.fps == 60.0
        assert fakes[1].props[cv2.CAP_PROP_FRAME_WIDTH] == 640
        assert src.read().bgr.shape == (240, 320, 3)

    def test_camera_without_device(self):
        with pytest.raises(InputError, match="names no device"):
            open_source("camera:")

    def test_missing(self, tmp_path):
        with pytest.raises(InputError, match="input not found"):
            open_source(tmp_path / "nothing.avi")

    def test_empty_folder(self, tmp_path):
        (tmp_path / "e").mkdir()
        with pytest.raises(InputError, match="nothing to read"):
            open_source(tmp_path / "e")

    def test_unsupported_file(self, tmp_path):
        (tmp_path / "x.csv").write_text("a,b")
        with pytest.raises(InputError, match="unsupported input file type '.csv'"):
            open_source(tmp_path / "x.csv")
