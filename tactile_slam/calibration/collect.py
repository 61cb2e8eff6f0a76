"""Guided collection of a calibration set from a live sensor.

The user is prompted to clear the sensor (the background is the float mean of
``background_frames`` frames, saved as uint8), then to press each ball at new places;
each accepted press is saved as ``<d.ddd>mm/<n>/gelsight.png`` and listed in
``catalog.csv`` (the layout of :mod:`tactile_slam.calibration.catalog`). A press that
shows no contact is refused and asked for again.

The capture object is injected: anything with ``read() -> (ok, frame)`` works, such as
``cv2.VideoCapture`` or a fake device in tests. Frames larger than the working size are
cropped and resized as for live capture (method.md section 1.1).
"""

from __future__ import annotations

import csv
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

import cv2
import numpy as np

from tactile_slam.calibration.catalog import BACKGROUND_NAME, CATALOG_HEADER, PRESS_IMAGE_NAME, CalibrationDataError
from tactile_slam.calibration.labels import NoContactError, detect_contact_circle


class Capture(Protocol):
    def read(self) -> tuple[bool, np.ndarray]: ...


@dataclass(frozen=True)
class CollectPlan:
    """What to collect: ball diameters (mm), presses per ball, the working image ``shape``
    ``(H, W)``, ``mm_per_px`` and the maximum indentation (mm) for the contact check."""

    diameters_mm: tuple[float, ...]
    presses_per_ball: int
    shape: tuple[int, int]
    mm_per_px: float
    max_indentation_mm: float = 2.0
    background_frames: int = 10
    max_retries: int = 3


def crop_resize(frame: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """Live-capture preprocessing: crop ``h//7`` rows and ``w//7`` columns from each side,
    trim to 4:3 from the top/left, resize bilinearly to ``shape`` ``(H, W)``. Frames already
    of ``shape`` are returned unchanged."""
    if frame.shape[:2] == tuple(shape):
        return frame
    h, w = frame.shape[:2]
    f = frame[h // 7: h - h // 7, w // 7: w - w // 7]
    h, w = f.shape[:2]
    if w * 3 > h * 4:
        f = f[:, w - h * 4 // 3:]
    else:
        f = f[h - w * 3 // 4:, :]
    return cv2.resize(f, (shape[1], shape[0]), interpolation=cv2.INTER_LINEAR)


def _grab(capture: Capture, shape: tuple[int, int]) -> np.ndarray:
    ok, frame = capture.read()
    if not ok or frame is None:
        raise CalibrationDataError("camera returned no frame (is the sensor connected and the index right?)")
    if frame.ndim != 3 or frame.shape[2] != 3:
        raise CalibrationDataError(f"camera frame must be BGR (H, W, 3), got {frame.shape}")
    return crop_resize(frame, shape)


def collect_calibration(
    out_dir: str | Path,
    capture: Capture,
    plan: CollectPlan,
    prompt: Callable[[str], str] = input,
    say: Callable[[str], None] = print,
) -> Path:
    """Run the guided session and write the calibration folder; returns ``catalog.csv``.

    ``prompt(message)`` waits for the user (Enter continues; ``q`` ends the current ball
    early); ``say`` reports progress.

    Raises:
        CalibrationDataError: the output folder already holds a catalog, the camera fails,
            or a press shows no contact after ``plan.max_retries`` tries.
    """
    out = Path(out_dir)
    if (out / "catalog.csv").exists():
        raise CalibrationDataError(f"{out} already holds a catalog.csv; choose an empty folder")
    out.mkdir(parents=True, exist_ok=True)
    prompt(f"Remove everything from the sensor, then press Enter to record {plan.background_frames} background frames")
    frames = np.stack([_grab(capture, plan.shape).astype(np.float32) for _ in range(plan.background_frames)])
    background = frames.mean(axis=0)
    spread = float(np.abs(frames - background).max())
    if spread > 25:
        say(f"warning: background frames differ by up to {spread:.0f} grey levels; was something touching the gel?")
    cv2.imwrite(str(out / BACKGROUND_NAME), background.astype(np.uint8))
    rows = []
    for d in plan.diameters_mm:
        ball_r = d / plan.mm_per_px / 2
        for n in range(plan.presses_per_ball):
            answer = prompt(f"{d:.2f} mm ball, press {n + 1}/{plan.presses_per_ball}: press it at a new place "
                            f"(cover the whole gel over the session), hold, press Enter (q: next ball)")
            if answer.strip().lower() == "q":
                break
            for attempt in range(plan.max_retries):
                img = _grab(capture, plan.shape)
                try:
                    detect_contact_circle(img, background, ball_r, plan.max_indentation_mm / plan.mm_per_px)
                    break
                except NoContactError:
                    if attempt == plan.max_retries - 1:
                        raise CalibrationDataError(
                            f"no contact visible in {plan.max_retries} tries for {d} mm press {n + 1}") from None
                    prompt("no contact visible: press the ball into the gel, hold, press Enter")
            reldir = f"{d:.3f}mm/{n}"
            (out / reldir).mkdir(parents=True, exist_ok=True)
            cv2.imwrite(str(out / reldir / PRESS_IMAGE_NAME), img)
            rows.append((reldir, f"{d:g}"))
            say(f"saved {reldir}")
    if not rows:
        raise CalibrationDataError("no press was recorded")
    path = out / "catalog.csv"
    with path.open("w", newline="") as f:
        wr = csv.writer(f)
        wr.writerow(CATALOG_HEADER)
        wr.writerows(rows)
    say(f"wrote {len(rows)} presses to {path}")
    return path
