"""Video files: a reader (:class:`VideoSource`) and a lossless writer (:func:`write_video`).

Recordings are FFV1 AVI at the working size (method.md section 1.1); any container and
codec that OpenCV's FFmpeg backend decodes is readable. Random access is exact; nearby
frames ahead are reached by decoding forward, because an OpenCV seek restarts decoding
a few dozen frames before its target.
"""

from __future__ import annotations

import os
from collections.abc import Iterable, Iterator
from pathlib import Path

import cv2
import numpy as np
import torch

from tactile_slam.geometry.frame import InputError
from tactile_slam.io.frames import RawFrame, SequenceSource

VIDEO_SUFFIXES = (".avi", ".mkv", ".mp4", ".mov", ".m4v", ".webm")
# Random access decodes forward over gaps up to this many frames instead of seeking.
MAX_SKIP = 24


def resize_bgr(image: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """Bilinear resize of an ``(h, w, 3)`` uint8 image to ``shape = (H, W)``."""
    if tuple(image.shape[:2]) == tuple(shape):
        return image
    return cv2.resize(image, (shape[1], shape[0]), interpolation=cv2.INTER_LINEAR)


def fit_to_shape(image: np.ndarray, shape: tuple[int, int] | None, resize: bool, where: str) -> np.ndarray:
    """Return ``image`` at ``shape`` (resized only when ``resize``), else raise naming ``where``."""
    if shape is None or tuple(image.shape[:2]) == tuple(shape):
        return image
    if not resize:
        h, w = image.shape[:2]
        raise InputError(
            f"{where}: frames are {w}x{h} but the working size is {shape[1]}x{shape[0]} "
            "(pass resize=True, or --resize on the command line, to resize them)"
        )
    return resize_bgr(image, shape)


def _open_capture(path: Path) -> cv2.VideoCapture:
    cap = cv2.VideoCapture(str(path), cv2.CAP_FFMPEG)
    if not cap.isOpened():
        cap.release()
        raise InputError(f"cannot open video {path}: not a video file or an unsupported codec")
    return cap


class VideoSource(SequenceSource):
    """Frames of a video file, with video index and timestamp ``index / fps``.

    Args:
        path: the video file.
        shape: expected ``(H, W)``; ``None`` accepts the video's own size.
        resize: resize frames of another size to ``shape`` bilinearly instead of
            raising :class:`InputError`.
        fps: overrides the container's frame rate (required if it has none).

    Raises:
        InputError: missing, unreadable or empty video, wrong frame size, no frame rate.
    """

    def __init__(
        self,
        path: str | Path,
        shape: tuple[int, int] | None = None,
        resize: bool = False,
        fps: float | None = None,
    ):
        self.path = Path(path)
        self.name = str(self.path)
        if not self.path.is_file():
            raise InputError(f"video file not found: {self.path}")
        if self.path.stat().st_size == 0:
            raise InputError(f"video file is empty (0 bytes): {self.path}")
        cap = _open_capture(self.path)
        try:
            count = int(cap.get(cv2.CAP_PROP_FRAME_COUNT))
            native_fps = float(cap.get(cv2.CAP_PROP_FPS))
            ok, first = cap.read()
            if not ok or first is None:
                raise InputError(f"video {self.path} contains no readable frames")
            if count <= 0:  # container without a frame count: count by decoding
                count = 1
                while cap.grab():
                    count += 1
        finally:
            cap.release()
        self._count = count
        if fps is None:
            if not (np.isfinite(native_fps) and native_fps > 0):
                raise InputError(f"video {self.path} has no frame rate; pass fps")
            fps = native_fps
        if not fps > 0:
            raise InputError(f"fps must be > 0, got {fps}")
        self.fps = float(fps)
        self.native_shape = (int(first.shape[0]), int(first.shape[1]))
        fit_to_shape(first, shape, resize, str(self.path))
        self.shape = tuple(shape) if shape is not None else self.native_shape
        self.resize = resize
        self._cap: cv2.VideoCapture | None = None
        self._cap_pid: int | None = None
        self._forked_caps: list[cv2.VideoCapture] = []
        self._next = 0

    def __len__(self) -> int:
        return self._count

    def _decoded(self, image: np.ndarray | None, ok: bool, index: int) -> RawFrame:
        if not ok or image is None:
            raise InputError(
                f"cannot decode frame {index} of {self._count} in {self.path} (file truncated or corrupt)"
            )
        bgr = fit_to_shape(image, self.shape, self.resize, f"{self.path} frame {index}")
        return RawFrame(index=index, timestamp=index / self.fps, bgr=bgr)

    def frame(self, position: int) -> RawFrame:
        # One capture per process (DataLoader workers reopen it). A short jump ahead
        # decodes forward; anything else seeks, which in OpenCV costs about as much as
        # decoding MAX_SKIP frames (it restarts decoding well before the target).
        self._drop_inherited()
        if self._cap is None:
            self._cap, self._cap_pid, self._next = _open_capture(self.path), os.getpid(), 0
        if 0 <= position - self._next <= MAX_SKIP:
            while self._next < position and self._cap.grab():
                self._next += 1
        if position != self._next:
            self._cap.set(cv2.CAP_PROP_POS_FRAMES, position)
        ok, image = self._cap.read()
        self._next = position + 1
        return self._decoded(image, ok, position)

    def iter_from(self, start: int) -> Iterator[RawFrame]:
        """Stream frames ``start, start + 1, ...`` with a private capture."""
        cap = _open_capture(self.path)
        try:
            if start:
                cap.set(cv2.CAP_PROP_POS_FRAMES, start)
            for index in range(start, self._count):
                ok, image = cap.read()
                yield self._decoded(image, ok, index)
        finally:
            cap.release()

    def __iter__(self) -> Iterator[RawFrame]:
        return self.iter_from(0)

    def _drop_inherited(self) -> None:
        # A capture inherited through fork (DataLoader workers): its decoder threads
        # do not exist in this process and releasing it would wait on them forever.
        # Keep it referenced and never touch it.
        if self._cap is not None and self._cap_pid != os.getpid():
            self._forked_caps.append(self._cap)
            self._cap = None

    def close(self) -> None:
        self._drop_inherited()
        if self._cap is not None:
            self._cap.release()
            self._cap = None

    def __getstate__(self) -> dict:
        state = self.__dict__.copy()
        state["_cap"], state["_cap_pid"], state["_forked_caps"] = None, None, []
        return state


def _frame_problem(frame: np.ndarray, size: tuple[int, int] | None) -> str | None:
    if frame.ndim != 3 or frame.shape[2] != 3 or frame.dtype != np.uint8:
        return f"must be (H, W, 3) uint8, got {frame.shape} {frame.dtype}"
    if size is not None and (frame.shape[1], frame.shape[0]) != size:
        return f"is {frame.shape[1]}x{frame.shape[0]}, earlier frames are {size[0]}x{size[1]}"
    if frame.shape[0] % 2 or frame.shape[1] % 2:  # OpenCV's FFV1 writer drops the odd row / column
        return (f"is {frame.shape[1]}x{frame.shape[0]}: the lossless video needs an even width and height "
                "(resize or crop the frames first)")
    return None


def write_video(path: str | Path, frames: np.ndarray | torch.Tensor | Iterable, fps: float) -> int:
    """Write BGR frames to a lossless FFV1 video (read back bit-exactly).

    Args:
        path: output file, normally ``.avi``; parent folders are created.
        frames: ``(T, H, W, 3)`` uint8 array or tensor, or an iterable of ``(H, W, 3)``
            uint8 frames (streamed, so long videos need not fit in memory).
        fps: frame rate stored in the container.

    Returns:
        The number of frames written.

    Raises:
        InputError: no frames, a frame that is not ``(H, W, 3)`` uint8, frames of
            different sizes or of an odd width or height (no file is left behind), or a
            file OpenCV cannot create.
        Whatever the iterable raises (a camera that disconnects, Ctrl-C): the frames
            written so far are kept as a valid video.
    """
    path = Path(path)
    if not fps > 0:
        raise InputError(f"fps must be > 0, got {fps}")
    if isinstance(frames, (np.ndarray, torch.Tensor)) and frames.ndim != 4:
        raise InputError(f"expected frames of shape (T, H, W, 3), got {tuple(frames.shape)}")
    path.parent.mkdir(parents=True, exist_ok=True)
    writer: cv2.VideoWriter | None = None
    size: tuple[int, int] | None = None
    count = 0
    bad_frame = False
    try:
        for frame in frames:
            frame = np.asarray(frame.detach().cpu() if isinstance(frame, torch.Tensor) else frame)
            problem = _frame_problem(frame, size)
            if problem is not None:
                bad_frame = True
                raise InputError(f"frame {count} for {path} {problem}")
            if writer is None:
                size = (frame.shape[1], frame.shape[0])
                writer = cv2.VideoWriter(str(path), cv2.CAP_FFMPEG, cv2.VideoWriter_fourcc(*"FFV1"), float(fps), size)
                if not writer.isOpened():
                    raise InputError(f"cannot create video {path} (FFV1 writer failed to open)")
            writer.write(np.ascontiguousarray(frame))
            count += 1
    finally:
        if writer is not None:
            writer.release()
            if bad_frame:
                path.unlink(missing_ok=True)
    if count == 0:
        raise InputError(f"no frames to write to {path}")
    return count
