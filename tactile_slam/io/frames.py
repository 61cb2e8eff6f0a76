"""The record every source yields (:class:`RawFrame`) and the source interfaces.

A source delivers frames in video order. Two kinds exist:

* :class:`FrameSource`: a stream (iteration only; ``len()`` may be unknown), e.g. a
  live camera;
* :class:`SequenceSource`: a finite recording with random access by position
  (``source[i]``) and ``len()``; iteration reads the frames in order. Only these can
  back a :class:`tactile_slam.io.dataset.FrameDataset`.

Positions (``source[i]``) count the frames a source delivers; ``RawFrame.index`` is the
frame's index in the underlying video, which differs when a source skips frames (a
scan skips its background window).
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np
import torch

from tactile_slam.geometry.frame import InputError

Array = np.ndarray | torch.Tensor


@dataclass
class RawFrame:
    """One input frame before any geometry.

    Exactly one of ``bgr`` (image sources) or ``gradients`` (gradient-map sequences)
    is set; ``contact`` accompanies ``gradients`` when the sequence has masks.

    Attributes:
        index: index of the frame in its video or sequence (0-based).
        timestamp: seconds since the start of the recording (index / fps for files,
            a monotonic clock for live cameras).
        bgr: ``(H, W, 3)`` uint8 image in OpenCV channel order.
        gradients: ``(H, W, 2)`` float32 slopes ``(dh/dx, dh/dy)``.
        contact: ``(H, W)`` bool contact mask, used as the eroded mask as-is.
    """

    index: int
    timestamp: float
    bgr: Array | None = None
    gradients: Array | None = None
    contact: Array | None = None

    def __post_init__(self) -> None:
        if (self.bgr is None) == (self.gradients is None):
            raise InputError("a RawFrame carries exactly one of bgr or gradients")
        if self.contact is not None and self.gradients is None:
            raise InputError("a RawFrame contact mask needs gradients")

    @property
    def kind(self) -> str:
        """``"bgr"`` or ``"gradients"``."""
        return "bgr" if self.bgr is not None else "gradients"

    @property
    def shape(self) -> tuple[int, int]:
        """``(H, W)`` of the frame."""
        data = self.bgr if self.bgr is not None else self.gradients
        return (int(data.shape[0]), int(data.shape[1]))


class FrameSource(ABC):
    """A stream of :class:`RawFrame` in video order.

    Attributes every source sets: ``fps`` (frames per second), ``shape`` (``(H, W)`` of
    the frames it yields) and ``name`` (the file, folder or device, for messages).
    Sources that hold OS resources release them in :meth:`close`; all are context
    managers.
    """

    fps: float
    shape: tuple[int, int]
    name: str

    @abstractmethod
    def __iter__(self) -> Iterator[RawFrame]:
        """Yield the frames in order, holding at most a few in memory."""

    def close(self) -> None:
        """Release files or devices held open (no-op by default)."""

    def __enter__(self) -> "FrameSource":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __repr__(self) -> str:
        h, w = self.shape
        return f"{type(self).__name__}({self.name!r}, {w}x{h}, {self.fps:g} fps)"


class SequenceSource(FrameSource):
    """A finite recording: ``len()``, random access ``source[i]`` and ordered iteration."""

    @abstractmethod
    def __len__(self) -> int:
        """Number of frames the source delivers."""

    @abstractmethod
    def frame(self, position: int) -> RawFrame:
        """The frame at ``0 <= position < len(self)`` (already range-checked)."""

    def __getitem__(self, position: int) -> RawFrame:
        n = len(self)
        if not isinstance(position, (int, np.integer)):
            raise TypeError(f"frame positions are integers, got {type(position).__name__}")
        position = int(position)
        if position < 0:
            position += n
        if not 0 <= position < n:
            raise IndexError(f"frame {position} out of range for {self.name} with {n} frames")
        return self.frame(position)

    def __iter__(self) -> Iterator[RawFrame]:
        for position in range(len(self)):
            yield self.frame(position)
