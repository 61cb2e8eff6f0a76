import cv2
import numpy as np
import pytest

from tactile_slam.io import ImageFolder, InputError
from tactile_slam.io.images import natural_key


def write_images(folder, frames, names):
    folder.mkdir(parents=True, exist_ok=True)
    for frame, name in zip(frames, names):
        assert cv2.imwrite(str(folder / name), frame)
    return folder


class TestNaturalKey:
    def test_orders_numbers_by_value(self):
        names = ["f10.png", "f2.png", "f1.png", "F3.png", "g0.png", "f2_b.png", "f9.png"]
        expected = ["f1.png", "f2.png", "f2_b.png", "F3.png", "f9.png", "f10.png", "g0.png"]
        assert sorted(names, key=natural_key) == expected


class TestImageFolder:
    def test_natural_order_indices_timestamps(self, tmp_path, frames):
        names = [f"frame_{i}.png" for i in range(12)]
        folder = write_images(tmp_path / "imgs", frames[:12], names)
        src = ImageFolder(folder, fps=10)
        assert len(src) == 12 and src.shape == (48, 64) and src.fps == 10
        got = list(src)
        assert [f.index for f in got] == list(range(12))
        assert np.allclose([f.timestamp for f in got], np.arange(12) / 10)
        for i, f in enumerate(got):  # frame_10 comes after frame_9, not after frame_1
            assert np.array_equal(f.bgr, frames[i])

    def test_mixed_formats_and_other_files(self, tmp_path, frames):
        folder = write_images(tmp_path / "imgs", frames[:3], ["0.png", "1.BMP", "2.png"])
        (folder / "notes.txt").write_text("ignored")
        (folder / "sub").mkdir()
        src = ImageFolder(folder, fps=25)
        assert len(src) == 3
        assert np.array_equal(src[1].bgr, frames[1])

    def test_jpeg_and_grey(self, tmp_path, frames):
        folder = tmp_path / "imgs"
        folder.mkdir()
        cv2.imwrite(str(folder / "a.jpg"), frames[0])
        cv2.imwrite(str(folder / "b.png"), frames[1][..., 0])
        src = ImageFolder(folder, fps=25)
        assert src[0].bgr.shape == (48, 64, 3) and src[1].bgr.shape == (48, 64, 3)
        assert np.array_equal(src[1].bgr[..., 2], frames[1][..., 0])

    def test_expected_shape(self, tmp_path, frames):
        folder = write_images(tmp_path / "imgs", frames[:2], ["a.png", "b.png"])
        with pytest.raises(InputError, match="a.png: frames are 64x48 but the working size is 320x240"):
            ImageFolder(folder, fps=25, shape=(240, 320))
        src = ImageFolder(folder, fps=25, shape=(24, 32), resize=True)
        assert np.array_equal(src[1].bgr, cv2.resize(frames[1], (32, 24), interpolation=cv2.INTER_LINEAR))

    def test_size_change_inside_folder(self, tmp_path, frames):
        folder = write_images(tmp_path / "imgs", [frames[0], frames[1][:24, :32]], ["a.png", "b.png"])
        src = ImageFolder(folder, fps=25)
        with pytest.raises(InputError, match="b.png: frames are 32x24 but the working size is 64x48"):
            src[1]

    def test_missing_folder(self, tmp_path):
        with pytest.raises(InputError, match="image folder not found"):
            ImageFolder(tmp_path / "nope", fps=25)

    def test_no_images(self, tmp_path):
        (tmp_path / "e").mkdir()
        (tmp_path / "e" / "readme.txt").write_text("x")
        with pytest.raises(InputError, match="no images"):
            ImageFolder(tmp_path / "e", fps=25)

    def test_unreadable_image(self, tmp_path, frames):
        folder = write_images(tmp_path / "imgs", frames[:1], ["a.png"])
        (folder / "b.png").write_bytes(b"not a png")
        src = ImageFolder(folder, fps=25)
        with pytest.raises(InputError, match="cannot read image .*b.png"):
            list(src)

    def test_bad_fps(self, tmp_path, frames):
        folder = write_images(tmp_path / "imgs", frames[:1], ["a.png"])
        with pytest.raises(InputError, match="fps"):
            ImageFolder(folder, fps=0)
