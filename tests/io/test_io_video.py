import pickle

import cv2
import numpy as np
import pytest
import torch

from tactile_slam.io import InputError, VideoSource, write_video


class TestWriteVideo:
    def test_round_trip_is_bit_exact(self, tmp_path, frames):
        path = tmp_path / "v.avi"
        assert write_video(path, frames, fps=25) == len(frames)
        # read back with plain OpenCV, independently of VideoSource
        cap = cv2.VideoCapture(str(path))
        back = []
        while True:
            ok, image = cap.read()
            if not ok:
                break
            back.append(image)
        cap.release()
        assert np.array_equal(np.stack(back), frames)

    def test_random_content_is_bit_exact(self, tmp_path):
        noise = np.random.default_rng(0).integers(0, 256, (5, 24, 32, 3), dtype=np.uint8)
        write_video(tmp_path / "n.avi", noise, fps=10)
        assert np.array_equal(np.stack([f.bgr for f in VideoSource(tmp_path / "n.avi")]), noise)

    def test_iterable_and_tensor_input(self, tmp_path, frames):
        write_video(tmp_path / "a.avi", (f for f in frames), fps=25)
        write_video(tmp_path / "b.avi", torch.from_numpy(frames), fps=25)
        for name in ("a.avi", "b.avi"):
            assert np.array_equal(np.stack([f.bgr for f in VideoSource(tmp_path / name)]), frames)

    def test_creates_parent_folders(self, tmp_path, frames):
        write_video(tmp_path / "x" / "y" / "v.avi", frames[:2], fps=25)
        assert (tmp_path / "x" / "y" / "v.avi").is_file()

    def test_no_frames(self, tmp_path):
        with pytest.raises(InputError, match="no frames"):
            write_video(tmp_path / "v.avi", [], fps=25)

    def test_bad_frame_leaves_no_file(self, tmp_path, frames):
        bad = [frames[0], frames[1].astype(np.float32)]
        with pytest.raises(InputError, match="frame 1 .* uint8"):
            write_video(tmp_path / "v.avi", bad, fps=25)
        assert not (tmp_path / "v.avi").exists()

    @pytest.mark.parametrize("shape", [(23, 32), (24, 31), (239, 321)])
    def test_odd_sizes_are_refused_not_cropped(self, tmp_path, shape):
        """OpenCV's FFV1 writer would drop the odd row or column, so the video would not
        read back as written."""
        with pytest.raises(InputError, match=f"{shape[1]}x{shape[0]}: the lossless video needs an even"):
            write_video(tmp_path / "v.avi", np.zeros((2, *shape, 3), np.uint8), fps=25)
        assert not (tmp_path / "v.avi").exists()

    def test_source_error_keeps_frames_written(self, tmp_path, frames):
        def disconnecting():
            yield from frames[:5]
            raise InputError("camera unplugged")

        with pytest.raises(InputError, match="unplugged"):
            write_video(tmp_path / "v.avi", disconnecting(), fps=25)
        assert np.array_equal(np.stack([f.bgr for f in VideoSource(tmp_path / "v.avi")]), frames[:5])

    def test_size_change(self, tmp_path, frames):
        with pytest.raises(InputError, match="frame 1 .* 32x24, earlier frames are 64x48"):
            write_video(tmp_path / "v.avi", [frames[0], frames[1, :24, :32]], fps=25)

    def test_wrong_array_rank(self, tmp_path, frames):
        with pytest.raises(InputError, match=r"\(T, H, W, 3\)"):
            write_video(tmp_path / "v.avi", frames[0], fps=25)

    def test_bad_fps(self, tmp_path, frames):
        with pytest.raises(InputError, match="fps"):
            write_video(tmp_path / "v.avi", frames, fps=0)


@pytest.fixture
def video(tmp_path, frames):
    path = tmp_path / "v.avi"
    write_video(path, frames, fps=20)
    return path


class TestVideoSource:
    def test_smoke(self, video, frames):
        src = VideoSource(video)
        assert len(src) == len(frames)
        assert src.shape == (48, 64)
        assert src.fps == 20
        assert "v.avi" in repr(src)

    def test_indices_and_timestamps(self, video, frames):
        got = list(VideoSource(video))
        assert [f.index for f in got] == list(range(len(frames)))
        assert np.allclose([f.timestamp for f in got], np.arange(len(frames)) / 20.0)
        assert all(f.bgr.dtype == np.uint8 and f.bgr.shape == (48, 64, 3) for f in got)

    def test_random_access_matches_stream(self, video, frames):
        src = VideoSource(video)
        for i in (7, 3, 4, 13, 0, -1):
            f = src[i]
            assert f.index == i % len(frames)
            assert np.array_equal(f.bgr, frames[i])

    def test_far_jumps_seek_exactly(self, tmp_path, gel_frames):
        long = gel_frames(60, (24, 32), noise=2.0, seed=4)
        write_video(tmp_path / "long.avi", long, fps=25)
        src = VideoSource(tmp_path / "long.avi")
        for i in (0, 50, 51, 20, 59, 1, 30):
            assert np.array_equal(src[i].bgr, long[i])

    def test_index_out_of_range(self, video):
        src = VideoSource(video)
        with pytest.raises(IndexError):
            src[14]
        with pytest.raises(TypeError):
            src[1.5]

    def test_fps_override(self, video):
        src = VideoSource(video, fps=50)
        assert src[5].timestamp == pytest.approx(0.1)

    def test_wrong_size(self, video):
        with pytest.raises(InputError, match="64x48 but the working size is 320x240"):
            VideoSource(video, shape=(240, 320))

    def test_resize_when_asked(self, video, frames):
        src = VideoSource(video, shape=(24, 32), resize=True)
        f = src[2]
        assert f.bgr.shape == (24, 32, 3)
        expected = cv2.resize(frames[2], (32, 24), interpolation=cv2.INTER_LINEAR)
        assert np.array_equal(f.bgr, expected)

    def test_pickle_reopens(self, video, frames):
        src = VideoSource(video)
        src[3]
        clone = pickle.loads(pickle.dumps(src))
        assert np.array_equal(clone[4].bgr, frames[4])
        src.close()

    def test_missing(self, tmp_path):
        with pytest.raises(InputError, match="not found: .*missing.avi"):
            VideoSource(tmp_path / "missing.avi")

    def test_empty_file(self, tmp_path):
        (tmp_path / "e.avi").write_bytes(b"")
        with pytest.raises(InputError, match="empty .*e.avi"):
            VideoSource(tmp_path / "e.avi")

    def test_unreadable_file(self, tmp_path):
        (tmp_path / "g.avi").write_bytes(b"this is not a video" * 100)
        with pytest.raises(InputError, match="g.avi"):
            VideoSource(tmp_path / "g.avi")

    def test_truncated_file(self, tmp_path):
        big = np.random.default_rng(1).integers(0, 256, (20, 48, 64, 3), dtype=np.uint8)
        path = tmp_path / "t.avi"
        write_video(path, big, fps=25)
        data = path.read_bytes()
        path.write_bytes(data[: len(data) // 2])
        with pytest.raises(InputError, match="t.avi"):
            list(VideoSource(path))
