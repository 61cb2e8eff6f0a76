import warnings

import cv2
import numpy as np
import pytest
import torch
import yaml

from tactile_slam.config import Config, ConfigError
from tactile_slam.io import BackgroundWarning, InputError, Scan, check_background, write_video

MINI = (240, 320)


def make_scan(folder, frames, fps=25):
    folder.mkdir(parents=True, exist_ok=True)
    write_video(folder / "gelsight.avi", frames, fps=fps)
    return folder


@pytest.fixture
def scan_frames(gel_frames):
    return gel_frames(13, MINI, noise=1.5, seed=7)


class TestScan:
    def test_smoke(self, tmp_path, scan_frames):
        with warnings.catch_warnings():
            warnings.simplefilter("error", BackgroundWarning)
            scan = Scan(make_scan(tmp_path / "s", scan_frames))
        assert len(scan) == 3 and scan.start == 10
        assert scan.shape == MINI and scan.fps == 25
        assert scan.background.shape == (240, 320, 3) and scan.background.dtype == np.float32
        assert scan.background_check.ok

    def test_background_is_float_mean(self, tmp_path, scan_frames):
        scan = Scan(make_scan(tmp_path / "s", scan_frames))
        expected = scan_frames[:10].astype(np.float64).mean(axis=0)
        np.testing.assert_allclose(scan.background, expected, atol=1e-4)
        # a float mean, not truncated to uint8
        assert not np.allclose(scan.background, np.floor(scan.background))

    def test_frames_keep_video_indices(self, tmp_path, scan_frames):
        scan = Scan(make_scan(tmp_path / "s", scan_frames, fps=20))
        got = list(scan)
        assert [f.index for f in got] == [10, 11, 12]
        assert np.allclose([f.timestamp for f in got], [0.5, 0.55, 0.6])
        for f in got:
            assert np.array_equal(f.bgr, scan_frames[f.index])
        assert scan[0].index == 10 and scan[-1].index == 12
        assert np.array_equal(scan[1].bgr, scan_frames[11])

    def test_contact_during_background_warns(self, tmp_path, scan_frames, press):
        pressed = press(scan_frames, 4, center=(100, 200), radius=25, amplitude=15)
        with pytest.warns(BackgroundWarning, match="frame 4"):
            scan = Scan(make_scan(tmp_path / "s", pressed))
        c = scan.background_check
        assert not c.ok and c.frame == 4
        assert (c.row - 100) ** 2 + (c.col - 200) ** 2 < 25**2

    def test_contact_after_background_does_not_warn(self, tmp_path, scan_frames, press):
        pressed = press(scan_frames, 11, center=(100, 200), radius=25, amplitude=40)
        with warnings.catch_warnings():
            warnings.simplefilter("error", BackgroundWarning)
            Scan(make_scan(tmp_path / "s", pressed))

    def test_background_png_overrides(self, tmp_path, scan_frames):
        folder = make_scan(tmp_path / "s", scan_frames)
        cv2.imwrite(str(folder / "background.png"), scan_frames[12])
        scan = Scan(folder)
        assert np.array_equal(scan.background, scan_frames[12].astype(np.float32))
        assert scan.start == 0 and len(scan) == 13 and scan.background_check is None
        assert [f.index for f in scan][:2] == [0, 1]

    @pytest.mark.parametrize("kind", ["numpy", "torch"])
    def test_background_argument_overrides(self, tmp_path, scan_frames, kind):
        folder = make_scan(tmp_path / "s", scan_frames)
        cv2.imwrite(str(folder / "background.png"), scan_frames[12])
        bg = np.full((240, 320, 3), 7.5, np.float32)
        scan = Scan(folder, background=torch.from_numpy(bg) if kind == "torch" else bg)
        assert np.array_equal(scan.background, bg)

    def test_gelslam_config_is_honoured(self, tmp_path, gel_frames):
        frames = gel_frames(12, (120, 160), seed=2)
        folder = make_scan(tmp_path / "s", frames)
        layout = {
            "device_config": {"device_name": "GelSight Mini", "ppmm": 0.0634, "imgh": 120, "imgw": 160,
                              "raw_imgh": 2464, "raw_imgw": 3280, "framerate": 25},
            "contact_mask_config": {"color_dist_threshold": 12, "height_threshold": 0.15},
        }
        (folder / "config.yaml").write_text(yaml.safe_dump(layout))
        scan = Scan(folder)
        assert scan.shape == (120, 160) and len(scan) == 2
        assert scan.config.sensor.mm_per_px == pytest.approx(0.0634)
        assert scan.config.contact.color_dist_threshold == 12
        # the default GelSight Mini size would have rejected these frames
        with pytest.raises(InputError, match="160x120 but the working size is 320x240"):
            Scan(folder, config=Config())

    def test_explicit_config_wins_over_folder(self, tmp_path, scan_frames):
        folder = make_scan(tmp_path / "s", scan_frames)
        (folder / "config.yaml").write_text(yaml.safe_dump({"sensor": {"width": 160, "height": 120}}))
        cfg = Config()
        cfg.sensor.background_frames = 5
        scan = Scan(folder, config=cfg)
        assert scan.start == 5 and len(scan) == 8

    def test_resize(self, tmp_path, gel_frames):
        folder = make_scan(tmp_path / "s", gel_frames(11, (300, 400), noise=0.5, seed=1))
        scan = Scan(folder, resize=True)
        assert scan[0].bgr.shape == (240, 320, 3) and scan.background.shape == (240, 320, 3)


class TestScanErrors:
    def test_missing_folder(self, tmp_path):
        with pytest.raises(InputError, match="scan folder not found"):
            Scan(tmp_path / "nope")

    def test_missing_video(self, tmp_path):
        (tmp_path / "s").mkdir()
        with pytest.raises(InputError, match="has no gelsight.avi"):
            Scan(tmp_path / "s")

    def test_video_shorter_than_background_window(self, tmp_path, scan_frames):
        with pytest.raises(InputError, match="7 frames, fewer than the 10-frame background window"):
            Scan(make_scan(tmp_path / "s", scan_frames[:7]))

    def test_only_background_frames(self, tmp_path, scan_frames):
        with pytest.raises(InputError, match="no frames after its 10-frame background window"):
            Scan(make_scan(tmp_path / "s", scan_frames[:10]))

    def test_empty_video(self, tmp_path):
        (tmp_path / "s").mkdir()
        (tmp_path / "s" / "gelsight.avi").write_bytes(b"")
        with pytest.raises(InputError, match="empty"):
            Scan(tmp_path / "s")

    def test_missing_background_file(self, tmp_path, scan_frames):
        folder = make_scan(tmp_path / "s", scan_frames)
        with pytest.raises(InputError, match="background image not found: .*bg.png"):
            Scan(folder, background=tmp_path / "bg.png")

    def test_unreadable_background_file(self, tmp_path, scan_frames):
        folder = make_scan(tmp_path / "s", scan_frames)
        (folder / "background.png").write_bytes(b"garbage")
        with pytest.raises(InputError, match="cannot read background image"):
            Scan(folder)

    def test_background_wrong_size(self, tmp_path, scan_frames):
        folder = make_scan(tmp_path / "s", scan_frames)
        with pytest.raises(InputError, match="background is 160x120 but frames are 320x240"):
            Scan(folder, background=np.zeros((120, 160, 3), np.float32))

    def test_background_nan(self, tmp_path, scan_frames):
        folder = make_scan(tmp_path / "s", scan_frames)
        bg = np.zeros((240, 320, 3), np.float32)
        bg[3, 4, 1] = np.nan
        with pytest.raises(InputError, match="NaN"):
            Scan(folder, background=bg)

    def test_bad_config_yaml(self, tmp_path, scan_frames):
        folder = make_scan(tmp_path / "s", scan_frames)
        (folder / "config.yaml").write_text("sensor: {nonsense_key: 3}")
        with pytest.raises(ConfigError, match="nonsense_key"):
            Scan(folder)


class TestCheckBackground:
    @pytest.mark.parametrize("noise", [0.0, 0.5, 2.0, 4.0])
    def test_noise_alone_passes(self, gel_frames, noise):
        assert check_background(gel_frames(10, (120, 160), noise=noise, seed=5)).ok

    @pytest.mark.parametrize("noise", [0.5, 2.0])
    def test_contact_is_found(self, gel_frames, press, noise):
        frames = press(gel_frames(10, (120, 160), noise=noise, seed=5), 6, (60, 40), 15, 10)
        c = check_background(frames)
        assert not c.ok and c.frame == 6
        assert (c.row - 60) ** 2 + (c.col - 40) ** 2 < 15**2

    def test_threshold_grows_with_noise(self, gel_frames):
        low = check_background(gel_frames(10, (120, 160), noise=1.0, seed=5))
        high = check_background(gel_frames(10, (120, 160), noise=4.0, seed=5))
        assert high.threshold > 2 * low.threshold
        assert high.noise_sigma > 2 * low.noise_sigma

    def test_single_hot_pixel_is_ignored(self, gel_frames):
        frames = gel_frames(10, (120, 160), noise=1.0, seed=5)
        frames[3, 50, 50] = 255 - frames[3, 50, 50]
        assert check_background(frames).ok

    def test_needs_two_frames(self, gel_frames):
        with pytest.raises(InputError, match="N >= 2"):
            check_background(gel_frames(1, (12, 16)))


class TestRealSensorImages:
    """The background check on real GelSight Mini images (../shared)."""

    @pytest.fixture
    def real(self, mini_data):
        calib = mini_data / "calibration"
        background = cv2.imread(str(calib / "background.png"))
        rows = (calib / "catalog.csv").read_text().splitlines()[1:3]
        presses = [cv2.imread(str(calib / row.split(",")[0] / "gelsight.png")) for row in rows]
        assert background is not None and all(p is not None for p in presses)
        return background, presses

    @staticmethod
    def noisy(image, n, seed):
        rng = np.random.default_rng(seed)
        return np.clip(np.round(image[None] + rng.normal(0, 1.5, (n, *image.shape))), 0, 255).astype(np.uint8)

    def test_untouched_window_passes(self, tmp_path, real):
        background, presses = real
        frames = np.concatenate([self.noisy(background, 10, 0), self.noisy(presses[0], 2, 1)])
        with warnings.catch_warnings():
            warnings.simplefilter("error", BackgroundWarning)
            scan = Scan(make_scan(tmp_path / "s", frames))
        assert np.abs(scan.background - background).mean() < 0.5  # noise averages out
        assert np.array_equal(scan[0].bgr, frames[10])

    @pytest.mark.parametrize("which", [0, 1])
    def test_real_press_in_window_warns(self, tmp_path, real, which):
        background, presses = real
        frames = np.concatenate([self.noisy(background, 10, 0), self.noisy(presses[which], 2, 1)])
        frames[6] = frames[10]  # the press, during the background window
        with pytest.warns(BackgroundWarning, match="frame 6"):
            scan = Scan(make_scan(tmp_path / "s", frames))
        c = scan.background_check
        # the most deviant pixel lies where the press changed the colour most
        dist = np.linalg.norm(presses[which].astype(np.float32) - background, axis=-1)
        assert dist[c.row, c.col] > 15
