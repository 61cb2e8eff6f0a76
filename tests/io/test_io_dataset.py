import numpy as np
import pytest
import torch
from torch.utils.data import DataLoader

from tactile_slam.io import (
    FrameBatch,
    FrameDataset,
    GradientSequence,
    InputError,
    RawFrame,
    VideoSource,
    collate,
    iter_batches,
    write_video,
)


@pytest.fixture
def video(tmp_path, frames):
    write_video(tmp_path / "v.avi", frames, fps=25)
    return VideoSource(tmp_path / "v.avi")


@pytest.fixture
def gradient_seq(tmp_path):
    rng = np.random.default_rng(0)
    g = rng.normal(0, 0.1, (5, 12, 16, 2)).astype(np.float32)
    c = rng.random((5, 12, 16)) > 0.5
    np.savez(tmp_path / "g.npz", gradients=g, contact=c)
    return GradientSequence(tmp_path / "g.npz", fps=25), g, c


class TestRawFrame:
    def test_kinds(self):
        assert RawFrame(0, 0.0, bgr=np.zeros((4, 5, 3), np.uint8)).shape == (4, 5)
        f = RawFrame(1, 0.1, gradients=np.zeros((4, 5, 2), np.float32))
        assert f.kind == "gradients" and f.shape == (4, 5)

    def test_exactly_one_payload(self):
        with pytest.raises(InputError, match="exactly one"):
            RawFrame(0, 0.0)
        with pytest.raises(InputError, match="exactly one"):
            RawFrame(0, 0.0, bgr=np.zeros((4, 5, 3), np.uint8), gradients=np.zeros((4, 5, 2), np.float32))
        with pytest.raises(InputError, match="contact mask needs gradients"):
            RawFrame(0, 0.0, bgr=np.zeros((4, 5, 3), np.uint8), contact=np.zeros((4, 5), bool))


class TestCollate:
    def test_bgr(self, video, frames):
        batch = collate([video[i] for i in (2, 5, 6)])
        assert batch.bgr.shape == (3, 48, 64, 3) and batch.bgr.dtype == torch.uint8
        assert batch.gradients is None and batch.contact is None
        assert torch.equal(batch.index, torch.tensor([2, 5, 6]))
        assert batch.timestamp.dtype == torch.float64
        assert torch.allclose(batch.timestamp, torch.tensor([2, 5, 6], dtype=torch.float64) / 25)
        assert torch.equal(batch.bgr[1], torch.from_numpy(frames[5]))
        assert len(batch) == 3

    def test_gradients(self, gradient_seq):
        src, g, c = gradient_seq
        batch = collate(list(src))
        assert batch.bgr is None
        assert batch.gradients.shape == (5, 12, 16, 2) and batch.gradients.dtype == torch.float32
        assert batch.contact.shape == (5, 12, 16) and batch.contact.dtype == torch.bool
        assert torch.equal(batch.gradients, torch.from_numpy(g)) and torch.equal(batch.contact, torch.from_numpy(c))

    def test_tensor_payloads(self):
        frames = [RawFrame(i, i / 10, bgr=torch.full((4, 5, 3), i, dtype=torch.uint8)) for i in range(3)]
        assert collate(frames).bgr[:, 0, 0, 0].tolist() == [0, 1, 2]

    def test_gradients_without_contact(self):
        frames = [RawFrame(i, 0.0, gradients=np.zeros((4, 5, 2), np.float32)) for i in range(2)]
        batch = collate(frames)
        assert batch.contact is None and batch.gradients.shape == (2, 4, 5, 2)

    def test_errors(self):
        bgr = RawFrame(0, 0.0, bgr=np.zeros((4, 5, 3), np.uint8))
        small = RawFrame(1, 0.0, bgr=np.zeros((3, 5, 3), np.uint8))
        grad = RawFrame(2, 0.0, gradients=np.zeros((4, 5, 2), np.float32))
        masked = RawFrame(3, 0.0, gradients=np.zeros((4, 5, 2), np.float32), contact=np.zeros((4, 5), bool))
        with pytest.raises(InputError, match="empty"):
            collate([])
        with pytest.raises(InputError, match="image frames with gradient frames"):
            collate([bgr, grad])
        with pytest.raises(InputError, match="different sizes"):
            collate([bgr, small])
        with pytest.raises(InputError, match="with and without contact"):
            collate([grad, masked])

    def test_to_device(self, gradient_seq, device):
        batch = collate(list(gradient_seq[0])).to(device)
        assert batch.gradients.device.type == device.type and batch.index.device.type == device.type
        assert batch.bgr is None


class TestFrameDataset:
    def test_dataloader_batches(self, video, frames):
        loader = DataLoader(FrameDataset(video), batch_size=4, collate_fn=collate)
        batches = list(loader)
        assert [len(b) for b in batches] == [4, 4, 4, 2]
        assert all(isinstance(b, FrameBatch) for b in batches)
        assert batches[0].bgr.shape == (4, 48, 64, 3)
        assert torch.equal(torch.cat([b.index for b in batches]), torch.arange(14))
        assert torch.equal(torch.cat([b.bgr for b in batches]), torch.from_numpy(frames))

    def test_shuffled_random_access(self, video, frames):
        loader = DataLoader(FrameDataset(video), batch_size=5, shuffle=True, collate_fn=collate,
                            generator=torch.Generator().manual_seed(0))
        for batch in loader:
            for i, image in zip(batch.index.tolist(), batch.bgr):
                assert torch.equal(image, torch.from_numpy(frames[i]))

    def test_worker_processes(self, video, gradient_seq, frames):
        video[3]  # the parent's open capture must not be shared with forked workers
        loader = DataLoader(FrameDataset(video), batch_size=7, num_workers=2, collate_fn=collate)
        assert torch.equal(torch.cat([b.bgr for b in loader]), torch.from_numpy(frames))
        src, g, _ = gradient_seq
        loader = DataLoader(FrameDataset(src), batch_size=2, num_workers=2, collate_fn=collate)
        assert torch.equal(torch.cat([b.gradients for b in loader]), torch.from_numpy(g))

    @pytest.mark.parametrize("save", [np.savez, np.savez_compressed], ids=["stored", "compressed"])
    def test_npz_in_worker_processes(self, tmp_path, save):
        """Forked workers inherit the parent's open zip stream, whose file position they
        share: frames larger than the read buffers came back wrong (stored) or failed to
        decompress (compressed), and the parent's reads broke after them."""
        rng = np.random.default_rng(1)
        g = rng.normal(0, 0.1, (40, 96, 128, 2)).astype(np.float32)
        c = rng.random((40, 96, 128)) > 0.5
        save(tmp_path / "g.npz", gradients=g, contact=c)
        src = GradientSequence(tmp_path / "g.npz", fps=25)
        assert np.array_equal(src[5].gradients, g[5])  # the parent's stream is open and has moved
        loader = DataLoader(FrameDataset(src), batch_size=3, num_workers=2, collate_fn=collate)
        batches = list(loader)
        assert torch.equal(torch.cat([b.gradients for b in batches]), torch.from_numpy(g))
        assert torch.equal(torch.cat([b.contact for b in batches]), torch.from_numpy(c))
        for i in (2, 39, 6):
            assert np.array_equal(src[i].gradients, g[i]) and np.array_equal(src[i].contact, c[i])

    def test_len_and_index(self, video):
        ds = FrameDataset(video)
        assert len(ds) == 14 and ds[13].index == 13


class TestIterBatches:
    def test_stream(self, video, frames):
        batches = list(iter_batches(video, 5))
        assert [len(b) for b in batches] == [5, 5, 4]
        assert torch.equal(batches[2].index, torch.tensor([10, 11, 12, 13]))
        assert torch.equal(torch.cat([b.bgr for b in batches]), torch.from_numpy(frames))

    def test_bad_batch_size(self, video):
        with pytest.raises(InputError, match="batch_size"):
            next(iter_batches(video, 0))

    def test_empty_stream(self):
        assert list(iter_batches([], 3)) == []

    def test_frames_read_before_a_corrupt_one_are_kept(self, video):
        """A source that fails at frame 12 first gives the frames read since the last full
        batch (10, 11), then its error."""
        def failing():
            for frame in video:
                if frame.index == 12:
                    raise InputError("cannot decode frame 12")
                yield frame

        batches = iter_batches(failing(), 5)
        assert [b.index.tolist() for b in (next(batches), next(batches), next(batches))] == \
            [[0, 1, 2, 3, 4], [5, 6, 7, 8, 9], [10, 11]]
        with pytest.raises(InputError, match="frame 12"):
            next(batches)
