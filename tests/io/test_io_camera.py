import itertools

import cv2
import numpy as np
import pytest

from tactile_slam.io import CameraSource, FrameDataset, InputError, crop_box, crop_raw, find_camera, list_video_devices

MINI_RAW = (2464, 3280)
MINI = (240, 320)


class FakeCapture:
    """Stands in for cv2.VideoCapture: synthetic raw frames, optionally failing."""

    def __init__(self, raw_shape=MINI_RAW, n_frames=None, opened=True):
        self.raw_shape = raw_shape
        self.n_frames = n_frames
        self.opened = opened
        self.props: dict[int, float] = {}
        self.reads = 0
        self.released = False

    def isOpened(self):
        return self.opened

    def set(self, prop, value):
        self.props[prop] = value
        return True

    def read(self):
        if self.released or (self.n_frames is not None and self.reads >= self.n_frames):
            return False, None
        h, w = self.raw_shape
        raw = np.full((h, w, 3), 255, np.uint8)  # border: white
        top, bottom, left, right = crop_box(self.raw_shape, MINI)
        raw[top:bottom, left:right] = (self.reads % 256, 50, 100)  # sensing area: varies per frame
        self.reads += 1
        return True, raw

    def release(self):
        self.released = True


def fake_clock(start=100.0, step=0.04):
    counter = itertools.count()
    return lambda: start + step * next(counter)


class TestCropBox:
    def test_gelsight_mini(self):
        # 2464 // 7 = 352 rows, 3280 // 7 = 468 columns off each side leaves 1760 x 2344;
        # 4:3 needs 2344 * 3 / 4 = 1758 rows, so 2 more rows go from the top.
        assert crop_box(MINI_RAW, MINI) == (354, 2112, 468, 2812)

    def test_digit(self):
        # 480 // 7 = 68, 640 // 7 = 91: 344 x 458 -> 458 * 3 // 4 = 343 rows, 1 from the top.
        assert crop_box((480, 640), MINI) == (69, 412, 91, 549)

    def test_too_wide_trims_columns_from_left(self):
        # 700 // 7 = 100, 2800 // 7 = 400: 500 x 2000 -> 500 * 4 / 3 = 666 columns.
        assert crop_box((700, 2800), MINI) == (100, 600, 2400 - 666, 2400)

    @pytest.mark.parametrize("seed", range(3))
    def test_properties(self, seed):
        rng = np.random.default_rng(seed)
        for h, w in rng.integers(40, 4000, (200, 2)):
            top, bottom, left, right = crop_box((int(h), int(w)), MINI)
            assert bottom == h - h // 7 and right == w - w // 7
            assert top >= h // 7 and left >= w // 7
            assert top == h // 7 or left == w // 7  # only one side is trimmed
            rows, cols = bottom - top, right - left
            assert abs(cols * 3 - rows * 4) < 4  # 4:3 to within a pixel

    def test_too_small(self):
        with pytest.raises(InputError, match="too small"):
            crop_box((1, 1), MINI)


class TestCropRaw:
    def test_matches_crop_then_bilinear_resize(self):
        raw = np.random.default_rng(0).integers(0, 256, (*MINI_RAW, 3), dtype=np.uint8)
        expected = cv2.resize(raw[354:2112, 468:2812], (320, 240), interpolation=cv2.INTER_LINEAR)
        assert np.array_equal(crop_raw(raw, MINI), expected)


class TestCameraSource:
    def test_fake_mini_device(self):
        fake = FakeCapture()
        cam = CameraSource(0, shape=MINI, fps=25, raw_shape=MINI_RAW, open_capture=lambda i: fake, clock=fake_clock())
        assert fake.props[cv2.CAP_PROP_FOURCC] == cv2.VideoWriter_fourcc(*"MJPG")
        assert fake.props[cv2.CAP_PROP_BUFFERSIZE] == 1
        assert fake.props[cv2.CAP_PROP_FRAME_WIDTH] == 3280 and fake.props[cv2.CAP_PROP_FRAME_HEIGHT] == 2464
        got = list(itertools.islice(cam, 3))
        assert [f.index for f in got] == [0, 1, 2]
        assert np.allclose([f.timestamp for f in got], [0.04, 0.08, 0.12])
        for k, f in enumerate(got):
            assert f.bgr.shape == (240, 320, 3) and f.bgr.dtype == np.uint8
            # the white border never leaks into the working image
            assert (f.bgr == np.array([k, 50, 100], np.uint8)).all()
        cam.close()
        assert fake.released
        with pytest.raises(InputError, match="closed"):
            cam.read()

    def test_timestamps_are_monotonic_by_default(self):
        with CameraSource(0, open_capture=lambda i: FakeCapture((480, 640))) as cam:
            t = [f.timestamp for f in itertools.islice(cam, 4)]
        assert all(b >= a for a, b in zip(t, t[1:])) and t[0] >= 0

    def test_no_len_no_dataset(self):
        cam = CameraSource(0, open_capture=lambda i: FakeCapture((480, 640)))
        with pytest.raises(TypeError):
            len(cam)
        with pytest.raises(InputError, match="random access"):
            FrameDataset(cam)

    def test_disconnect(self):
        cam = CameraSource(3, open_capture=lambda i: FakeCapture((480, 640), n_frames=2))
        it = iter(cam)
        next(it), next(it)
        with pytest.raises(InputError, match="read failed on camera 3 after 2 frames"):
            next(it)

    def test_does_not_open(self):
        fake = FakeCapture(opened=False)
        with pytest.raises(InputError, match="cannot open camera 5"):
            CameraSource(5, open_capture=lambda i: fake)
        assert fake.released

    def test_by_name(self, tmp_path):
        sysfs = fake_sysfs(tmp_path)
        opened = []

        def open_capture(index):
            opened.append(index)
            return FakeCapture((480, 640))

        cam = CameraSource("GelSight Mini", open_capture=open_capture, sysfs_root=sysfs)
        assert opened == [2] and cam.device_index == 2 and "GelSight Mini" in cam.name

    def test_bad_fps(self):
        with pytest.raises(InputError, match="fps"):
            CameraSource(0, fps=0, open_capture=lambda i: FakeCapture())


def fake_sysfs(root):
    names = {
        "video0": "Integrated Camera: Integrated C",
        "video1": "Integrated Camera: Integrated I",
        "video2": "GelSight Mini R0B 2BJ3-1CJ2: Ge",
        "video3": "GelSight Mini R0B 2BJ3-1CJ2: Ge",
        "video10": "GelSight Mini R0B 2BJ3-1CJ2: Ge",
    }
    for node, name in names.items():
        (root / node).mkdir(parents=True)
        (root / node / "name").write_text(name + "\n")
    (root / "v4l-subdev0").mkdir()  # not a videoN node
    (root / "video7").mkdir()  # no name file
    return root


class TestDeviceLookup:
    def test_list(self, tmp_path):
        devices = list_video_devices(fake_sysfs(tmp_path))
        assert sorted(devices) == [0, 1, 2, 3, 10]
        assert devices[2] == "GelSight Mini R0B 2BJ3-1CJ2: Ge"

    def test_lowest_matching_node(self, tmp_path):
        sysfs = fake_sysfs(tmp_path)
        assert find_camera("GelSight Mini", sysfs) == 2
        assert find_camera("gelsight mini", sysfs) == 2
        assert find_camera("Integrated", sysfs) == 0

    def test_not_found_lists_devices(self, tmp_path):
        with pytest.raises(InputError, match="no camera named 'DIGIT'.*video0: 'Integrated Camera"):
            find_camera("DIGIT", fake_sysfs(tmp_path))

    def test_no_sysfs(self, tmp_path):
        with pytest.raises(InputError, match="devices: none"):
            find_camera("GelSight Mini", tmp_path / "missing")
