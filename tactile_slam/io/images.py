"""A folder of images as a recording, in natural name order (``2.png`` before ``10.png``)."""

from __future__ import annotations

import re
from pathlib import Path

import cv2

from tactile_slam.geometry.frame import InputError
from tactile_slam.io.frames import RawFrame, SequenceSource
from tactile_slam.io.video import fit_to_shape

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp")


def natural_key(name: str) -> tuple:
    """Sort key that orders digit runs by value: ``f2`` < ``f10``."""
    return tuple((0, int(part), part) if part.isdigit() else (1, 0, part.lower()) for part in re.split(r"(\d+)", name))


def list_images(folder: Path) -> list[Path]:
    """Image files directly in ``folder`` (png/jpg/jpeg/bmp, any case), naturally sorted."""
    files = [p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES]
    return sorted(files, key=lambda p: natural_key(p.name))


class ImageFolder(SequenceSource):
    """Images of a folder as frames ``0..N-1`` with timestamps ``index / fps``.

    Args:
        folder: folder of png/jpg/jpeg/bmp images (grey images are read as BGR).
        fps: frame rate the images were taken at.
        shape: expected ``(H, W)``; ``None`` accepts the first image's size.
        resize: resize images of another size to ``shape`` instead of raising.

    Raises:
        InputError: missing folder, no images, an unreadable image, wrong size.
    """

    def __init__(self, folder: str | Path, fps: float, shape: tuple[int, int] | None = None, resize: bool = False):
        self.folder = Path(folder)
        self.name = str(self.folder)
        if not self.folder.is_dir():
            raise InputError(f"image folder not found: {self.folder}")
        if not fps > 0:
            raise InputError(f"fps must be > 0, got {fps}")
        self.files = list_images(self.folder)
        if not self.files:
            raise InputError(f"no images ({'/'.join(IMAGE_SUFFIXES)}) in {self.folder}")
        self.fps = float(fps)
        self.resize = resize
        first = self._read(0)
        self.shape = tuple(shape) if shape is not None else (int(first.shape[0]), int(first.shape[1]))
        fit_to_shape(first, self.shape, resize, str(self.files[0]))

    def _read(self, position: int):
        path = self.files[position]
        image = cv2.imread(str(path), cv2.IMREAD_COLOR)
        if image is None:
            raise InputError(f"cannot read image {path}")
        return image

    def __len__(self) -> int:
        return len(self.files)

    def frame(self, position: int) -> RawFrame:
        bgr = fit_to_shape(self._read(position), self.shape, self.resize, str(self.files[position]))
        return RawFrame(index=position, timestamp=position / self.fps, bgr=bgr)
