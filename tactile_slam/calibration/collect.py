"""Guided collection of a calibration set from a live sensor.

The user is prompted to clear the sensor (the background is the float mean of
``background_frames`` frames, saved as uint8), then to press each ball at new places;
each accepted press is saved as ``<d.ddd>mm/<n>/gelsight.png`` and listed in
``catalog.csv`` (the layout of :mod:`tactile_slam.calibration.catalog`). A press that
shows no contact is refused and asked for again.

Frames come from an injected ``read_frame() -> (H, W, 3) uint8 BGR`` of the working size:
the CLI passes :class:`tactile_slam.io.camera.CameraSource` (which crops and resizes the
raw sensor frames, method.md section 1.1); tests pass a fake device.
"""

from __future__ import annotations

import csv
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from tactile_slam.calibration.catalog import BACKGROUND_NAME, CATALOG_HEADER, PRESS_IMAGE_NAME, CalibrationDataError
from tactile_slam.calibration.labels import NoContactError, detect_contact_circle


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


def _grab(read_frame: Callable[[], np.ndarray], shape: tuple[int, int]) -> np.ndarray:
    frame = read_frame()
    if frame is None or frame.shape != (*shape, 3):
        got = None if frame is None else frame.shape
        raise CalibrationDataError(f"camera frame must be BGR {(*shape, 3)}, got {got}")
    return frame


def collect_calibration(
    out_dir: str | Path,
    read_frame: Callable[[], np.ndarray],
    plan: CollectPlan,
    prompt: Callable[[str], str] = input,
    say: Callable[[str], None] = print,
) -> Path:
    """Run the guided session and write the calibration folder; returns ``catalog.csv``.

    ``prompt(message)`` waits for the user (Enter continues; ``q`` ends the current ball
    early); ``say`` reports progress.

    Raises:
        CalibrationDataError: the output folder already holds a catalog, a frame has the
            wrong size, or a press shows no contact after ``plan.max_retries`` tries.
        ValueError: whatever ``read_frame`` raises when the camera fails.
    """
    out = Path(out_dir)
    if (out / "catalog.csv").exists():
        raise CalibrationDataError(f"{out} already holds a catalog.csv; choose an empty folder")
    out.mkdir(parents=True, exist_ok=True)
    prompt(f"Remove everything from the sensor, then press Enter to record {plan.background_frames} background frames")
    frames = np.stack([_grab(read_frame, plan.shape).astype(np.float32) for _ in range(plan.background_frames)])
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
                img = _grab(read_frame, plan.shape)
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
