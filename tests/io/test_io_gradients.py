import io
import pickle
import zipfile
from pathlib import Path

import numpy as np
import pytest
import torch

from tactile_slam.bench.common import PeakMemory
from tactile_slam.io import GradientSequence, InputError
from tactile_slam.io.gradients import NpzFrames


def sequence(n=6, shape=(24, 32), seed=0):
    rng = np.random.default_rng(seed)
    gradients = rng.normal(0, 0.2, (n, *shape, 2)).astype(np.float32)
    contact = rng.random((n, *shape)) > 0.5
    return gradients, contact


def save_npy(folder, gradients, contact):
    folder.mkdir(parents=True, exist_ok=True)
    np.save(folder / "gradient_maps.npy", gradients)
    np.save(folder / "contact_masks.npy", contact)
    return folder


class TestNpyLayout:
    def test_folder(self, tmp_path):
        g, c = sequence()
        src = GradientSequence(save_npy(tmp_path / "trial", g, c), fps=25)
        assert len(src) == 6 and src.shape == (24, 32) and src.fps == 25
        got = list(src)
        assert [f.index for f in got] == list(range(6))
        assert np.allclose([f.timestamp for f in got], np.arange(6) / 25)
        for i, f in enumerate(got):
            assert f.kind == "gradients" and f.bgr is None
            assert f.gradients.dtype == np.float32 and f.contact.dtype == bool
            assert np.array_equal(f.gradients, g[i]) and np.array_equal(f.contact, c[i])

    def test_is_memory_mapped(self, tmp_path):
        g, c = sequence()
        src = GradientSequence(save_npy(tmp_path / "trial", g, c), fps=25)
        assert isinstance(src.gradients, np.memmap) and isinstance(src.contact, np.memmap)

    def test_npy_path_and_uint8_masks(self, tmp_path):
        g, c = sequence()
        folder = save_npy(tmp_path / "trial", g, c.astype(np.uint8))
        src = GradientSequence(folder / "gradient_maps.npy", fps=25)
        assert np.array_equal(src[3].contact, c[3]) and src[3].contact.dtype == bool

    def test_float64_input(self, tmp_path):
        g, c = sequence()
        src = GradientSequence(save_npy(tmp_path / "t", g.astype(np.float64), c), fps=25)
        assert src[1].gradients.dtype == np.float32

    def test_pickle_reopens_without_copying(self, tmp_path):
        g, c = sequence()
        src = GradientSequence(save_npy(tmp_path / "t", g, c), fps=25)
        blob = pickle.dumps(src)
        assert len(blob) < g.nbytes / 4
        assert np.array_equal(pickle.loads(blob)[2].gradients, g[2])

    def test_nan_frame(self, tmp_path):
        g, c = sequence()
        g[4, 3, 5, 1] = np.nan
        src = GradientSequence(save_npy(tmp_path / "t", g, c), fps=25)
        src[3]
        with pytest.raises(InputError, match="frame 4 contain NaN"):
            src[4]

    def test_missing_masks(self, tmp_path):
        g, _ = sequence()
        (tmp_path / "t").mkdir()
        np.save(tmp_path / "t" / "gradient_maps.npy", g)
        with pytest.raises(InputError, match="not found: .*contact_masks.npy"):
            GradientSequence(tmp_path / "t", fps=25)

    def test_missing_folder_contents(self, tmp_path):
        (tmp_path / "t").mkdir()
        with pytest.raises(InputError, match="not found: .*gradient_maps.npy"):
            GradientSequence(tmp_path / "t", fps=25)

    def test_corrupt_file(self, tmp_path):
        g, c = sequence()
        folder = save_npy(tmp_path / "t", g, c)
        (folder / "gradient_maps.npy").write_bytes(b"garbage")
        with pytest.raises(InputError, match="cannot read .*gradient_maps.npy"):
            GradientSequence(folder, fps=25)


class TestNpzLayout:
    @pytest.mark.parametrize("dtype", [np.float16, np.float32, np.float64])
    def test_dtypes(self, tmp_path, dtype):
        g, c = sequence()
        np.savez_compressed(tmp_path / "gt_gradients.npz", gradients=g.astype(dtype), contact=c)
        src = GradientSequence(tmp_path / "gt_gradients.npz", fps=30)
        f = src[5]
        assert f.gradients.dtype == np.float32 and f.index == 5 and f.timestamp == pytest.approx(5 / 30)
        np.testing.assert_allclose(f.gradients, g[5], rtol=1e-3 if dtype == np.float16 else 0, atol=1e-3)
        assert np.array_equal(f.contact, c[5])

    def test_missing_key(self, tmp_path):
        g, _ = sequence()
        np.savez(tmp_path / "x.npz", gradients=g)
        with pytest.raises(InputError, match=r"needs the arrays 'gradients' \+ 'contact' or 'gradient_maps' \+ "
                                             r"'contact_masks' \(found \['gradients'\]\)"):
            GradientSequence(tmp_path / "x.npz", fps=25)

    def test_npy_layout_names(self, tmp_path):
        """An ``.npz`` may use the ``.npy`` layout's array names; where it holds both pairs,
        ``gradients`` + ``contact`` are read."""
        g, c = sequence()
        np.savez_compressed(tmp_path / "x.npz", gradient_maps=g, contact_masks=c.astype(np.uint8))
        src = GradientSequence(tmp_path / "x.npz", fps=25)
        assert len(src) == len(g)
        np.testing.assert_array_equal(src[3].gradients, g[3])
        np.testing.assert_array_equal(src[3].contact, c[3])
        other, _ = sequence(seed=1)
        np.savez(tmp_path / "both.npz", gradient_maps=other, contact_masks=~c, gradients=g, contact=c)
        frame = GradientSequence(tmp_path / "both.npz", fps=25)[2]
        np.testing.assert_array_equal(frame.gradients, g[2])
        np.testing.assert_array_equal(frame.contact, c[2])

    def test_nan_frame_raises_when_read(self, tmp_path):
        g, c = sequence()
        g[2, 0, 0, 0] = np.inf
        np.savez(tmp_path / "x.npz", gradients=g, contact=c)
        src = GradientSequence(tmp_path / "x.npz", fps=25)
        src[1]
        with pytest.raises(InputError, match="frame 2 contain NaN or Inf"):
            src[2]

    @pytest.mark.parametrize("save", [np.savez, np.savez_compressed])
    def test_frames_in_any_order(self, tmp_path, save):
        """Streamed from the zip member: in order, backwards (the member is read again
        from its start) and by negative index, every frame is the saved one."""
        g, c = sequence(n=7)
        save(tmp_path / "x.npz", gradients=g.astype(np.float16), contact=c.astype(np.uint8))
        src = GradientSequence(tmp_path / "x.npz", fps=25)
        assert isinstance(src.gradients, NpzFrames) and len(src) == 7 and src.shape == (24, 32)
        for i in [0, 1, 2, 6, 3, 3, 0, -1]:
            f = src[i % 7]
            assert np.array_equal(f.gradients, g[i].astype(np.float16).astype(np.float32))
            assert f.contact.dtype == bool and np.array_equal(f.contact, c[i])
        with pytest.raises(IndexError):
            src.gradients[7]

    def test_pickle_reopens_without_copying(self, tmp_path):
        g, c = sequence()
        np.savez_compressed(tmp_path / "x.npz", gradients=g, contact=c)
        src = GradientSequence(tmp_path / "x.npz", fps=25)
        src[4]
        blob = pickle.dumps(src)
        assert len(blob) < 2000
        assert np.array_equal(pickle.loads(blob)[2].gradients, g[2])

    @pytest.mark.skipif(not Path("/proc/self/clear_refs").exists(), reason="needs Linux /proc")
    def test_opening_a_long_sequence_reads_nothing_ahead(self, tmp_path):
        """400 zero frames of 320x240 compress to almost nothing but are 250 MB as float32
        maps: opening and reading a frame must not decompress them all."""
        n, shape = 400, (240, 320)
        np.savez_compressed(tmp_path / "long.npz", gradients=np.zeros((n, *shape, 2), np.float32),
                            contact=np.zeros((n, *shape), bool))
        with PeakMemory() as mem:
            src = GradientSequence(tmp_path / "long.npz", fps=25)
            f = src[n - 1]
        assert f.gradients.shape == (*shape, 2) and not f.contact.any()
        assert mem.peak_mb - mem.start_mb < 50

    def test_truncated_member(self, tmp_path):
        """A member whose header promises more frames than it holds: the frames it holds
        read, the missing one is an error naming the file."""
        g, c = sequence(n=5)
        with zipfile.ZipFile(tmp_path / "x.npz", "w") as z:
            for key, arr, keep in (("gradients", g, 3), ("contact", c, 5)):
                buf = io.BytesIO()
                np.lib.format.write_array_header_1_0(buf, np.lib.format.header_data_from_array_1_0(arr))
                z.writestr(key + ".npy", buf.getvalue() + arr[:keep].tobytes())
        src = GradientSequence(tmp_path / "x.npz", fps=25)
        assert np.array_equal(src[2].gradients, g[2])
        with pytest.raises(InputError, match="x.npz.*ends inside frame 3"):
            src[3]

    def test_fortran_order_member(self, tmp_path):
        g, c = sequence()
        np.savez(tmp_path / "x.npz", gradients=np.asfortranarray(g), contact=c)
        with pytest.raises(InputError, match="cannot be read frame by frame"):
            GradientSequence(tmp_path / "x.npz", fps=25)

    def test_not_a_zip(self, tmp_path):
        (tmp_path / "x.npz").write_bytes(b"nope")
        with pytest.raises(InputError, match="cannot read"):
            GradientSequence(tmp_path / "x.npz", fps=25)

    def test_missing(self, tmp_path):
        with pytest.raises(InputError, match="not found"):
            GradientSequence(tmp_path / "x.npz", fps=25)


class TestShapes:
    @pytest.mark.parametrize(
        "g_shape, c_shape, message",
        [
            ((3, 24, 32, 2), (3, 24, 31), "do not match"),
            ((3, 24, 32, 2), (2, 24, 32), "do not match"),
            ((3, 24, 32, 3), (3, 24, 32), r"\(N, H, W, 2\)"),
            ((24, 32, 2), (24, 32), r"\(N, H, W, 2\)"),
            ((0, 24, 32, 2), (0, 24, 32), "empty"),
        ],
    )
    def test_bad_shapes(self, tmp_path, g_shape, c_shape, message):
        np.savez(tmp_path / "x.npz", gradients=np.zeros(g_shape, np.float32), contact=np.zeros(c_shape, bool))
        with pytest.raises(InputError, match=message):
            GradientSequence(tmp_path / "x.npz", fps=25)

    def test_integer_gradients(self, tmp_path):
        np.savez(tmp_path / "x.npz", gradients=np.zeros((2, 4, 4, 2), np.int32), contact=np.zeros((2, 4, 4), bool))
        with pytest.raises(InputError, match="floating point"):
            GradientSequence(tmp_path / "x.npz", fps=25)

    def test_wrong_working_size(self, tmp_path):
        g, c = sequence()
        np.savez(tmp_path / "x.npz", gradients=g, contact=c)
        with pytest.raises(InputError, match="32x24 but the working size is 320x240"):
            GradientSequence(tmp_path / "x.npz", fps=25, shape=(240, 320))

    def test_unknown_file_type(self, tmp_path):
        (tmp_path / "x.txt").write_text("x")
        with pytest.raises(InputError, match="not a gradient sequence"):
            GradientSequence(tmp_path / "x.txt", fps=25)


def test_feeds_frame_builder(tmp_path):
    """Batches of a gradient sequence are what FrameBuilder.from_gradients takes."""
    from tactile_slam.config import Config
    from tactile_slam.geometry.frame import FrameBuilder
    from tactile_slam.io import collate

    cfg = Config()
    cfg.sensor.height, cfg.sensor.width = 24, 32
    g, c = sequence()
    np.savez(tmp_path / "x.npz", gradients=g, contact=c)
    batch = collate([f for f in GradientSequence(tmp_path / "x.npz", fps=25, shape=cfg.sensor.shape)][:4])
    frame = FrameBuilder(cfg).from_gradients(batch.gradients, batch.contact, batch.index, batch.timestamp)
    assert frame.height.shape == (4, 24, 32)
    assert torch.equal(frame.index, torch.arange(4))
    assert torch.equal(frame.contact, torch.from_numpy(c[:4]))
