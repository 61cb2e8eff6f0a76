"""Live sensors through OpenCV capture (method.md section 1.1).

A device is chosen by index or by the V4L2 name it reports (``/sys/class/video4linux/
videoN/name`` contains e.g. ``"GelSight Mini"``). It is opened with the MJPG fourcc
and a one-frame buffer, so each read returns a fresh frame. Raw frames are cropped
(``floor(h/7)`` rows top and bottom, ``floor(w/7)`` columns each side, then extra rows
trimmed from the top or columns from the left to reach the working aspect ratio) and
resized bilinearly to the working size.

The capture is injectable (``open_capture``) so tests and other back-ends can stand
in for a physical device.
"""

from __future__ import annotations

import re
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Protocol

import cv2
import numpy as np

from tactile_slam.geometry.frame import InputError
from tactile_slam.io.frames import FrameSource, RawFrame
from tactile_slam.io.video import resize_bgr

SYSFS_VIDEO4LINUX = Path("/sys/class/video4linux")


class Capture(Protocol):
    """The part of ``cv2.VideoCapture`` a camera source uses."""

    def isOpened(self) -> bool: ...
    def set(self, prop: int, value: float) -> bool: ...
    def read(self) -> tuple[bool, np.ndarray | None]: ...
    def release(self) -> None: ...


def list_video_devices(sysfs_root: str | Path = SYSFS_VIDEO4LINUX) -> dict[int, str]:
    """``{N: name}`` for every ``videoN`` node under ``sysfs_root`` that reports a name."""
    root = Path(sysfs_root)
    devices = {}
    if not root.is_dir():
        return devices
    for node in root.iterdir():
        match = re.fullmatch(r"video(\d+)", node.name)
        name_file = node / "name"
        if match and name_file.is_file():
            try:
                devices[int(match.group(1))] = name_file.read_text().strip()
            except OSError:
                continue
    return devices


def find_camera(name: str, sysfs_root: str | Path = SYSFS_VIDEO4LINUX) -> int:
    """Index of the lowest-numbered V4L2 device whose name contains ``name``
    (case-insensitive). A sensor exposes several nodes; the lowest is its capture node.

    Raises:
        InputError: no device matches; the message lists the devices present.
    """
    devices = list_video_devices(sysfs_root)
    matches = sorted(i for i, dev in devices.items() if name.lower() in dev.lower())
    if not matches:
        present = ", ".join(f"video{i}: {dev!r}" for i, dev in sorted(devices.items())) or "none"
        raise InputError(f"no camera named {name!r} found under {sysfs_root} (devices: {present})")
    return matches[0]


def crop_box(raw_shape: tuple[int, int], shape: tuple[int, int]) -> tuple[int, int, int, int]:
    """Rows ``[top, bottom)`` and columns ``[left, right)`` of a raw frame that map to
    the working image.

    Args:
        raw_shape: ``(h, w)`` of the raw frame.
        shape: ``(H, W)`` of the working image, whose aspect ratio the box takes.

    Returns:
        ``(top, bottom, left, right)``.
    """
    h, w = raw_shape
    out_h, out_w = shape
    top, bottom, left, right = h // 7, h - h // 7, w // 7, w - w // 7
    rows, cols = bottom - top, right - left
    if cols * out_h > rows * out_w:  # too wide: trim columns from the left
        left = right - rows * out_w // out_h
    else:  # too tall: trim rows from the top
        top = bottom - cols * out_h // out_w
    if bottom <= top or right <= left:
        raise InputError(f"raw frame {w}x{h} is too small to crop")
    return top, bottom, left, right


def crop_raw(raw: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """``(h, w, 3)`` uint8 raw frame -> ``(H, W, 3)`` uint8 working image (crop + bilinear resize)."""
    top, bottom, left, right = crop_box(raw.shape[:2], shape)
    return resize_bgr(np.ascontiguousarray(raw[top:bottom, left:right]), shape)


def open_cv_capture(index: int) -> cv2.VideoCapture:
    """OpenCV capture of device ``index`` (V4L2 back-end on Linux)."""
    if sys.platform.startswith("linux"):
        return cv2.VideoCapture(index, cv2.CAP_V4L2)
    return cv2.VideoCapture(index)


class CameraSource(FrameSource):
    """Live frames from a camera; an endless stream (no ``len()``, no random access).

    Args:
        device: device index, or a name the V4L2 device name contains (e.g.
            ``"GelSight Mini"``).
        shape: working ``(H, W)`` the raw frames are cropped and resized to.
        fps: nominal frame rate (the sensor's; timestamps come from the clock).
        raw_shape: ``(h, w)`` to request from the device, or ``None`` to keep its mode.
        open_capture: ``index -> Capture``; ``None`` uses :func:`open_cv_capture`.
        sysfs_root: where V4L2 devices are listed (for name lookup).
        clock: monotonic clock in seconds; timestamps count from opening.

    Frames carry consecutive indices from 0 and ``clock() - (clock at opening)``.

    Raises:
        InputError: no device of that name, the device does not open, or a read fails
            (disconnected sensor).
    """

    def __init__(
        self,
        device: int | str,
        shape: tuple[int, int] = (240, 320),
        fps: float = 25.0,
        raw_shape: tuple[int, int] | None = None,
        open_capture: Callable[[int], Capture] | None = None,
        sysfs_root: str | Path = SYSFS_VIDEO4LINUX,
        clock: Callable[[], float] = time.monotonic,
    ):
        index = device if isinstance(device, int) else find_camera(device, sysfs_root)
        self.device_index = index
        self.name = f"camera {index}" if isinstance(device, int) else f"camera {index} ({device})"
        if not fps > 0:
            raise InputError(f"fps must be > 0, got {fps}")
        self.shape = tuple(shape)
        self.fps = float(fps)
        self.clock = clock
        cap = (open_capture or open_cv_capture)(index)
        if not cap.isOpened():
            cap.release()
            raise InputError(f"cannot open {self.name}")
        cap.set(cv2.CAP_PROP_FOURCC, cv2.VideoWriter_fourcc(*"MJPG"))
        cap.set(cv2.CAP_PROP_BUFFERSIZE, 1)
        if raw_shape is not None:
            cap.set(cv2.CAP_PROP_FRAME_WIDTH, raw_shape[1])
            cap.set(cv2.CAP_PROP_FRAME_HEIGHT, raw_shape[0])
        self._cap: Capture | None = cap
        self._t0 = clock()
        self._count = 0

    def read(self) -> RawFrame:
        """Grab, crop and resize the next frame.

        Raises:
            InputError: the source is closed or the device returned no frame.
        """
        if self._cap is None:
            raise InputError(f"{self.name} is closed")
        ok, raw = self._cap.read()
        timestamp = self.clock() - self._t0
        if not ok or raw is None or raw.ndim != 3 or raw.shape[2] != 3 or raw.size == 0:
            raise InputError(f"read failed on {self.name} after {self._count} frames (sensor disconnected?)")
        frame = RawFrame(index=self._count, timestamp=timestamp, bgr=crop_raw(raw, self.shape))
        self._count += 1
        return frame

    def __iter__(self) -> Iterator[RawFrame]:
        while True:
            yield self.read()

    def close(self) -> None:
        if self._cap is not None:
            self._cap.release()
            self._cap = None
