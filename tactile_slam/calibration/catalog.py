"""Calibration folder: ``catalog.csv``, ``background.png`` and one ``gelsight.png`` per press.

Layout (method.md section 2.1)::

    CALIB_DIR/background.png
    CALIB_DIR/catalog.csv            # header: experiment_reldir,diameter(mm)
    CALIB_DIR/<d.ddd>mm/<n>/gelsight.png

Paths are always resolved through the catalog. Every image is checked for existence,
readability and size (the background's size, and the sensor's when one is given).
"""

from __future__ import annotations

import csv
import hashlib
import re
import warnings
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

CATALOG_HEADER = ("experiment_reldir", "diameter(mm)")
BACKGROUND_NAME = "background.png"
PRESS_IMAGE_NAME = "gelsight.png"


class CalibrationDataError(ValueError):
    """A calibration folder, catalog, image or label is missing or malformed."""


class CatalogWarning(UserWarning):
    """A catalog row that reads but looks wrong (a press folder named for another diameter)."""


_FOLDER_DIAMETER = re.compile(r"^(\d+(?:\.(\d*))?)mm/")
"""A press folder ``<d.ddd>mm/...`` of the SDK's layout: the diameter, and its decimals."""


@dataclass(frozen=True)
class Press:
    """One ball press: ``reldir`` relative to the calibration folder, ball diameter in mm."""

    reldir: str
    diameter_mm: float
    image_path: Path

    def ball_radius_px(self, mm_per_px: float) -> float:
        """Ball radius in pixels, ``d / mm_per_px / 2``."""
        return self.diameter_mm / mm_per_px / 2.0


@dataclass
class CalibrationSet:
    """A validated calibration folder.

    ``background`` is ``(H, W, 3)`` float32 BGR; press images are read on demand by
    :meth:`image` as ``(H, W, 3)`` uint8 BGR.
    """

    root: Path
    background: np.ndarray
    presses: list[Press]

    @property
    def shape(self) -> tuple[int, int]:
        """``(H, W)`` of every image in the set."""
        return self.background.shape[:2]

    def image(self, press: Press) -> np.ndarray:
        """``(H, W, 3)`` uint8 BGR image of ``press``."""
        return read_image(press.image_path, self.shape)

    def press(self, reldir: str) -> Press:
        for p in self.presses:
            if p.reldir == reldir:
                return p
        raise CalibrationDataError(f"press {reldir!r} is not in {self.root / 'catalog.csv'}")

    def fingerprint(self) -> str:
        """SHA-256 (hex, 16 chars) over the catalog rows, background and press image bytes."""
        h = hashlib.sha256()
        h.update((self.root / BACKGROUND_NAME).read_bytes())
        for p in self.presses:
            h.update(f"{p.reldir},{p.diameter_mm}".encode())
            h.update(p.image_path.read_bytes())
        return h.hexdigest()[:16]


def read_image(path: Path, shape: tuple[int, int] | None = None) -> np.ndarray:
    """Read a BGR image as ``(H, W, 3)`` uint8, checking it exists and has ``shape`` = (H, W)."""
    path = Path(path)
    if not path.is_file():
        raise CalibrationDataError(f"image not found: {path}")
    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if img is None:
        raise CalibrationDataError(f"cannot decode image {path}")
    if shape is not None and img.shape[:2] != tuple(shape):
        raise CalibrationDataError(
            f"image {path} is {img.shape[1]}x{img.shape[0]} (WxH), expected {shape[1]}x{shape[0]}"
        )
    return img


def read_catalog(path: Path) -> list[tuple[str, float]]:
    """Rows ``(reldir, diameter_mm)`` of a ``catalog.csv``; validates header and values.

    The file may start with a UTF-8 byte-order mark and end its lines in CRLF; columns past
    the first two are ignored (a trailing comma makes an empty one), and backslashes in
    ``experiment_reldir`` (Windows paths) become ``/``.

    Warns:
        CatalogWarning: a press folder named ``<d>mm/...`` whose ``d``, to the name's
            decimals, is not the listed diameter.
    """
    path = Path(path)
    if not path.is_file():
        raise CalibrationDataError(f"catalog not found: {path} (expected header {','.join(CATALOG_HEADER)})")
    with path.open(newline="", encoding="utf-8-sig") as f:  # -sig: a byte-order mark is no part of the header
        rows = [r for r in csv.reader(f) if r and any(c.strip() for c in r)]
    if not rows or tuple(c.strip() for c in rows[0][:2]) != CATALOG_HEADER:
        raise CalibrationDataError(f"{path}: header must be {','.join(CATALOG_HEADER)}, got {rows[:1]}")
    out, seen, misnamed = [], set(), []
    for i, row in enumerate(rows[1:], start=2):
        if len(row) < 2:
            raise CalibrationDataError(f"{path}:{i}: expected 2 columns, got {row}")
        reldir = row[0].strip().replace("\\", "/")
        try:
            diameter = float(row[1])
        except ValueError as exc:
            raise CalibrationDataError(f"{path}:{i}: diameter {row[1]!r} is not a number") from exc
        if not np.isfinite(diameter) or diameter <= 0:
            raise CalibrationDataError(f"{path}:{i}: diameter must be > 0 mm, got {row[1]}")
        if reldir in seen:
            raise CalibrationDataError(f"{path}:{i}: press {reldir!r} listed twice")
        seen.add(reldir)
        out.append((reldir, diameter))
        named = _FOLDER_DIAMETER.match(reldir)
        if named and abs(float(named[1]) - diameter) > 0.5 * 10.0 ** -len(named[2] or "") + 1e-9:
            misnamed.append(f"{reldir} listed as {row[1].strip()} mm")
    if not out:
        raise CalibrationDataError(f"{path} lists no presses")
    if misnamed:
        warnings.warn(f"{path}: {len(misnamed)} press folder(s) named for another ball diameter than listed: "
                      f"{', '.join(misnamed[:5])}; a wrong diameter gives wrong training targets", CatalogWarning,
                      stacklevel=2)
    return out


def load_calibration_set(root: str | Path, shape: tuple[int, int] | None = None) -> CalibrationSet:
    """Read and validate a calibration folder.

    Args:
        root: the calibration folder.
        shape: expected ``(H, W)`` (e.g. ``SensorConfig.shape``); ``None`` accepts the
            background's size. Every press image must match it.

    Raises:
        CalibrationDataError: missing folder, catalog, background or image; a bad
            catalog row; an image of the wrong size.
    """
    root = Path(root)
    if not root.is_dir():
        raise CalibrationDataError(f"calibration folder not found: {root}")
    rows = read_catalog(root / "catalog.csv")
    background = read_image(root / BACKGROUND_NAME).astype(np.float32)
    if shape is not None and background.shape[:2] != tuple(shape):
        h, w = background.shape[:2]
        raise CalibrationDataError(
            f"{root / BACKGROUND_NAME} is {w}x{h} (WxH), expected {shape[1]}x{shape[0]}: presses recorded at "
            f"{w}x{h} need a sensor config with width {w}, height {h} and their mm_per_px (--config FILE)"
        )
    presses = [Press(r, d, root / r / PRESS_IMAGE_NAME) for r, d in rows]
    missing = [str(p.image_path) for p in presses if not p.image_path.is_file()]
    if missing:
        raise CalibrationDataError(f"{len(missing)} press image(s) missing, first: {missing[0]}")
    calib = CalibrationSet(root, background, presses)
    for p in presses:  # decode each once so size errors surface here, not mid-training
        calib.image(p)
    return calib
