"""Recorded scans: a folder holding ``gelsight.avi`` plus optional ``config.yaml``
(GelSLAM layout or ours) and ``background.png`` (method.md sections 1.1, 2.4, 5.2).

The first ``config.sensor.background_frames`` (10) frames of the video are contact-free
by protocol; their float mean is the background, and the scan's frames start after
them, keeping their true video indices. The window is validated: frames that differ
from their mean by more than the noise explains (contact during capture) trigger a
:class:`BackgroundWarning`. An explicit background (``background.png`` in the folder,
or the ``background`` argument) replaces the window, and then every video frame is data.
"""

from __future__ import annotations

import warnings
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import torch

from tactile_slam.config import Config
from tactile_slam.geometry.frame import InputError
from tactile_slam.io.frames import RawFrame, SequenceSource
from tactile_slam.io.video import VideoSource

VIDEO_NAME = "gelsight.avi"
CONFIG_NAME = "config.yaml"
BACKGROUND_NAME = "background.png"

# Chi distribution with 3 degrees of freedom (colour distance of i.i.d. Gaussian
# noise in B, G, R): its median is 1.5382 sigma. MAD -> sigma for a normal: 1.4826.
_MAD_TO_SIGMA = 1.4826


class BackgroundWarning(UserWarning):
    """The background frames differ from each other more than sensor noise explains."""


def is_grey(background: np.ndarray, levels: float = 2.0) -> bool:
    """Whether a ``(H, W, 3)`` BGR background has no colour: every pixel's channels within
    ``levels`` intensity levels of each other (a greyscale recording). The calibration
    decode reads the gel's colour lighting, so such frames cannot be decoded."""
    bg = np.asarray(background, dtype=np.float32)
    return bool((bg.max(axis=-1) - bg.min(axis=-1)).max() <= levels)


@dataclass(frozen=True)
class BackgroundCheck:
    """How much the background frames deviate from their mean.

    Attributes:
        max_deviation: largest local (5 x 5 median) BGR distance of a frame from the
            mean, in intensity levels.
        threshold: the level above which a deviation is not noise.
        frame: position within the window of the most deviant frame.
        row, col: pixel of the largest deviation.
        noise_sigma: robust spread of the local deviations (intensity levels).
    """

    max_deviation: float
    threshold: float
    frame: int
    row: int
    col: int
    noise_sigma: float

    @property
    def ok(self) -> bool:
        return self.max_deviation <= self.threshold


def mean_background(frames: np.ndarray) -> np.ndarray:
    """``(N, H, W, 3)`` uint8 frames -> ``(H, W, 3)`` float32 mean."""
    if frames.ndim != 4 or frames.shape[-1] != 3 or frames.shape[0] == 0:
        raise InputError(f"expected background frames of shape (N, H, W, 3), got {frames.shape}")
    return frames.astype(np.float64).mean(axis=0).astype(np.float32)


def check_background(frames: np.ndarray, n_sigma: float = 12.0, min_level: float = 2.0) -> BackgroundCheck:
    """Measure how far the background frames stray from their mean.

    Each frame's per-pixel BGR distance to the mean is median-filtered over 5 x 5
    pixels (so isolated hot or noisy pixels cannot trigger, while a contact, hundreds
    of pixels wide, survives). Over all frames and pixels these local
    deviations are mostly noise: the threshold is their median plus ``n_sigma`` robust
    standard deviations (MAD), and never below ``min_level`` intensity levels, the
    quantisation floor of uint8 video.

    Args:
        frames: ``(N, H, W, 3)`` uint8 or float background frames, ``N >= 2``.

    Returns:
        The largest deviation, where it is, and the threshold.
    """
    if frames.ndim != 4 or frames.shape[-1] != 3 or frames.shape[0] < 2:
        raise InputError(f"background check needs (N >= 2, H, W, 3) frames, got {frames.shape}")
    stack = frames.astype(np.float32)
    dist = np.linalg.norm(stack - stack.mean(axis=0), axis=-1)
    local = np.stack([cv2.medianBlur(d, 5) for d in dist.astype(np.float32)])
    median = float(np.median(local))
    sigma = _MAD_TO_SIGMA * float(np.median(np.abs(local - median)))
    threshold = max(median + n_sigma * sigma, min_level)
    frame, row, col = np.unravel_index(int(np.argmax(local)), local.shape)
    return BackgroundCheck(
        max_deviation=float(local[frame, row, col]),
        threshold=threshold,
        frame=int(frame),
        row=int(row),
        col=int(col),
        noise_sigma=sigma,
    )


def load_background(background: str | Path | np.ndarray | torch.Tensor, shape: tuple[int, int]) -> np.ndarray:
    """An explicit background (image path or ``(H, W, 3)`` array) as float32.

    Raises:
        InputError: missing or unreadable file, wrong size, NaN or Inf.
    """
    if isinstance(background, (str, Path)):
        path = Path(background)
        if not path.is_file():
            raise InputError(f"background image not found: {path}")
        image = cv2.imread(str(path), cv2.IMREAD_COLOR)
        if image is None:
            raise InputError(f"cannot read background image {path}")
        where = str(path)
    else:
        image = background.detach().cpu().numpy() if isinstance(background, torch.Tensor) else np.asarray(background)
        where = "background array"
    if image.ndim != 3 or image.shape[2] != 3:
        raise InputError(f"{where}: expected an (H, W, 3) BGR image, got shape {image.shape}")
    if tuple(image.shape[:2]) != tuple(shape):
        raise InputError(
            f"{where}: background is {image.shape[1]}x{image.shape[0]} but frames are {shape[1]}x{shape[0]}"
        )
    image = image.astype(np.float32)
    if not np.isfinite(image).all():
        raise InputError(f"{where}: background contains NaN or Inf")
    return image


class Scan(SequenceSource):
    """A recorded scan folder.

    Args:
        folder: holds ``gelsight.avi`` and optionally ``config.yaml`` and ``background.png``.
        config: overrides the folder's ``config.yaml``; with neither, the GelSight Mini
            preset.
        background: explicit background (image path or ``(H, W, 3)`` BGR array);
            overrides ``background.png``.
        resize: resize video frames of another size to the working size.

    Attributes:
        config: the configuration in force.
        background: ``(H, W, 3)`` float32 BGR background.
        background_check: the window's :class:`BackgroundCheck`, or ``None`` when the
            background was given explicitly.
        start: video index of the first data frame (the background window's length, or
            0 with an explicit background).
        video: the underlying :class:`VideoSource`.

    Raises:
        InputError: missing folder or video, unreadable video, wrong frame size, video
            not longer than the background window, bad explicit background.
        BackgroundWarning: (a warning) contact during the background window.
    """

    def __init__(
        self,
        folder: str | Path,
        config: Config | None = None,
        background: str | Path | np.ndarray | torch.Tensor | None = None,
        resize: bool = False,
    ):
        self.folder = Path(folder)
        self.name = str(self.folder)
        if not self.folder.is_dir():
            raise InputError(f"scan folder not found: {self.folder}")
        video_path = self.folder / VIDEO_NAME
        if not video_path.is_file():
            raise InputError(f"scan folder {self.folder} has no {VIDEO_NAME}")
        if config is None:
            config_path = self.folder / CONFIG_NAME
            config = Config.from_yaml(config_path) if config_path.is_file() else Config()
        self.config = config
        sensor = config.sensor
        self.video = VideoSource(video_path, shape=sensor.shape, resize=resize)
        self.fps = self.video.fps
        self.shape = self.video.shape
        if background is None and (self.folder / BACKGROUND_NAME).is_file():
            background = self.folder / BACKGROUND_NAME
        if background is not None:
            self.background = load_background(background, self.shape)
            self.background_check = None
            self.start = 0
        else:
            self._background_from_window(sensor.background_frames)
        if len(self) == 0:
            raise InputError(f"scan {self.folder} has no frames after its {self.start}-frame background window")

    def _background_from_window(self, n: int) -> None:
        if len(self.video) < n:
            raise InputError(
                f"video {self.video.path} has {len(self.video)} frames, fewer than the "
                f"{n}-frame background window"
            )
        stream = self.video.iter_from(0)
        try:
            window = np.stack([next(stream).bgr for _ in range(n)])
        finally:
            stream.close()
        self.background = mean_background(window)
        self.start = n
        self.background_check = check_background(window) if n >= 2 else None
        c = self.background_check
        if c is not None and not c.ok:
            warnings.warn(
                f"background frames of {self.video.path} differ: frame {c.frame} deviates by "
                f"{c.max_deviation:.1f} levels at row {c.row}, col {c.col} (noise threshold "
                f"{c.threshold:.1f}); was something touching the gel during the first {n} frames? "
                f"Pass an explicit background to override.",
                BackgroundWarning,
                stacklevel=3,
            )

    def __len__(self) -> int:
        return len(self.video) - self.start

    def frame(self, position: int) -> RawFrame:
        return self.video.frame(position + self.start)

    def __iter__(self) -> Iterator[RawFrame]:
        return self.video.iter_from(self.start)

    def close(self) -> None:
        self.video.close()
