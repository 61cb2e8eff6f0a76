"""Batched offline access: a ``torch.utils.data.Dataset`` over a recording, the
``collate`` that stacks :class:`RawFrame` records into a :class:`FrameBatch`, and a
streaming batcher for sources without random access."""

from __future__ import annotations

from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass, fields, replace

import numpy as np
import torch
from torch.utils.data import Dataset

from tactile_slam.geometry.frame import InputError
from tactile_slam.io.frames import RawFrame, SequenceSource


@dataclass
class FrameBatch:
    """``B`` stacked raw frames.

    Attributes:
        index: ``(B,)`` int64 video indices.
        timestamp: ``(B,)`` float64 seconds.
        bgr: ``(B, H, W, 3)`` uint8 images, or ``None`` for gradient sequences.
        gradients: ``(B, H, W, 2)`` float32 slopes, or ``None`` for image sources.
        contact: ``(B, H, W)`` bool masks, or ``None``.
    """

    index: torch.Tensor
    timestamp: torch.Tensor
    bgr: torch.Tensor | None = None
    gradients: torch.Tensor | None = None
    contact: torch.Tensor | None = None

    def __len__(self) -> int:
        return int(self.index.shape[0])

    def _map(self, fn) -> "FrameBatch":
        tensors = {f.name: getattr(self, f.name) for f in fields(self)}
        return replace(self, **{name: fn(t) for name, t in tensors.items() if t is not None})

    def to(self, device: torch.device | str) -> "FrameBatch":
        """Copy every tensor to ``device``."""
        return self._map(lambda t: t.to(device))

    def pin_memory(self) -> "FrameBatch":
        """Page-locked copy, so ``DataLoader(pin_memory=True)`` works."""
        return self._map(lambda t: t.pin_memory())


def _stack(frames: Sequence[RawFrame], attr: str, dtype: torch.dtype) -> torch.Tensor:
    items = [getattr(f, attr) for f in frames]
    if all(isinstance(x, np.ndarray) for x in items):
        # numpy's single-threaded copy: torch.stack's parallel copy of a few MB costs
        # far more on a loaded machine
        return torch.from_numpy(np.stack(items)).to(dtype)
    return torch.stack([torch.as_tensor(x) for x in items]).to(dtype)


def collate(frames: Sequence[RawFrame]) -> FrameBatch:
    """Stack raw frames of one kind and one size into a :class:`FrameBatch`.

    Usable as ``DataLoader(FrameDataset(source), batch_size=16, collate_fn=collate)``.
    """
    if len(frames) == 0:
        raise InputError("cannot collate an empty list of frames")
    kinds = {f.kind for f in frames}
    if len(kinds) > 1:
        raise InputError("cannot collate image frames with gradient frames")
    shapes = {f.shape for f in frames}
    if len(shapes) > 1:
        raise InputError(f"cannot collate frames of different sizes {sorted(shapes)}")
    with_contact = {f.contact is not None for f in frames}
    if len(with_contact) > 1:
        raise InputError("cannot collate gradient frames with and without contact masks")
    batch = FrameBatch(
        index=torch.tensor([f.index for f in frames], dtype=torch.int64),
        timestamp=torch.tensor([f.timestamp for f in frames], dtype=torch.float64),
    )
    if kinds == {"bgr"}:
        batch.bgr = _stack(frames, "bgr", torch.uint8)
    else:
        batch.gradients = _stack(frames, "gradients", torch.float32)
        if with_contact == {True}:
            batch.contact = _stack(frames, "contact", torch.bool)
    return batch


class FrameDataset(Dataset):
    """Random access to a recording for batched offline work.

    Args:
        source: a :class:`SequenceSource` (video, scan, image folder, gradient
            sequence). Live cameras have no random access and are rejected.

    ``dataset[i]`` is the source's ``i``-th :class:`RawFrame`; combine with
    :func:`collate` in a ``DataLoader``. Sources reopen their files in each worker.
    """

    def __init__(self, source: SequenceSource):
        if not isinstance(source, SequenceSource):
            raise InputError(
                f"FrameDataset needs a recording with random access, got {type(source).__name__}; "
                "iterate live sources with iter_batches instead"
            )
        self.source = source

    def __len__(self) -> int:
        return len(self.source)

    def __getitem__(self, i: int) -> RawFrame:
        return self.source[i]


def iter_batches(frames: Iterable[RawFrame], batch_size: int) -> Iterator[FrameBatch]:
    """Group a stream of frames into batches of ``batch_size`` (the last may be shorter).

    Memory stays bounded by one batch, so this works for live and long sources. When the
    source raises (a corrupt frame, or Ctrl+C while it reads), the frames read before it
    are yielded first as a shorter batch, then the error is raised: nothing already read
    is lost.
    """
    if batch_size < 1:
        raise InputError(f"batch_size must be >= 1, got {batch_size}")
    chunk: list[RawFrame] = []
    it = iter(frames)
    while True:
        try:
            frame = next(it)
        except StopIteration:
            break
        except (Exception, KeyboardInterrupt):
            if chunk:
                yield collate(chunk)
            raise
        chunk.append(frame)
        if len(chunk) == batch_size:
            yield collate(chunk)
            chunk = []
    if chunk:
        yield collate(chunk)
