"""Synthetic ball presses with a known contact circle, and calibration folders built from them.

The synthetic gel follows a sphere inside the contact radius ``a`` and relaxes outside
it (slope decaying exponentially with distance from the rim), as a real elastomer does;
colour changes linearly with the slope, plus seeded sensor noise.
"""

from __future__ import annotations

import csv
from pathlib import Path

import cv2
import numpy as np
import pytest

H, W = 240, 320
MM_PER_PX = 0.0634
COLOUR_GAIN = np.array([45.0, -30.0, 25.0])  # BGR change per unit slope along x
COLOUR_GAIN_Y = np.array([-20.0, 40.0, 30.0])  # ... and along y


def synthetic_background(seed: int = 0) -> np.ndarray:
    """``(H, W, 3)`` float32 smooth background with a vignette."""
    ys, xs = np.mgrid[0:H, 0:W].astype(np.float32)
    vign = 1.0 - 0.3 * (((xs - W / 2) / W) ** 2 + ((ys - H / 2) / H) ** 2)
    return np.stack([110 * vign, 95 * vign, 80 * vign], axis=-1).astype(np.float32)


def synthetic_slopes(cx: float, cy: float, a: float, ball_radius: float, decay: float = 6.0) -> np.ndarray:
    """``(H, W, 2)`` slopes: sphere inside radius ``a``, exponential relaxation outside."""
    ys, xs = np.mgrid[0:H, 0:W].astype(np.float64)
    dx, dy = xs - cx, ys - cy
    r = np.hypot(dx, dy)
    s_in = r / np.sqrt(np.maximum(ball_radius**2 - r**2, 1e-9))
    s_rim = a / np.sqrt(ball_radius**2 - a**2)
    s = np.where(r < a, s_in, s_rim * np.exp(-(r - a) / decay))
    with np.errstate(invalid="ignore", divide="ignore"):
        ux, uy = np.where(r > 0, dx / r, 0.0), np.where(r > 0, dy / r, 0.0)
    return np.stack([s * ux, s * uy], axis=-1)


def render(background: np.ndarray, slopes: np.ndarray, seed: int = 0, noise: float = 1.5) -> np.ndarray:
    """uint8 image: background + linear colour response to slopes + Gaussian noise."""
    rng = np.random.default_rng(seed)
    img = background + slopes[..., :1] * COLOUR_GAIN + slopes[..., 1:] * COLOUR_GAIN_Y
    img = img + rng.normal(0.0, noise, img.shape)
    return np.clip(np.round(img), 0, 255).astype(np.uint8)


def press_image(cx, cy, a, diameter_mm, seed=0, background=None):
    bg = synthetic_background() if background is None else background
    return render(bg, synthetic_slopes(cx, cy, a, diameter_mm / MM_PER_PX / 2), seed)


# (reldir, diameter, cx, cy, contact radius)
SYNTHETIC_PRESSES = [
    ("6.310mm/0", 6.31, 100.0, 80.0, 25.0),
    ("6.310mm/1", 6.31, 220.5, 150.3, 27.0),
    ("6.310mm/2", 6.31, 160.2, 120.7, 23.0),
    ("6.310mm/3", 6.31, 60.0, 170.0, 26.0),
    ("9.500mm/0", 9.5, 240.0, 70.0, 33.0),
    ("9.500mm/1", 9.5, 130.0, 180.0, 35.0),
]


def write_calibration_folder(root: Path, presses=SYNTHETIC_PRESSES) -> Path:
    """Write a synthetic calibration folder (background, catalog, press images)."""
    root.mkdir(parents=True, exist_ok=True)
    bg = synthetic_background()
    cv2.imwrite(str(root / "background.png"), np.round(bg).astype(np.uint8))
    with (root / "catalog.csv").open("w", newline="") as f:
        wr = csv.writer(f)
        wr.writerow(["experiment_reldir", "diameter(mm)"])
        for i, (reldir, d, cx, cy, a) in enumerate(presses):
            (root / reldir).mkdir(parents=True, exist_ok=True)
            cv2.imwrite(str(root / reldir / "gelsight.png"), press_image(cx, cy, a, d, seed=i + 1, background=bg))
            wr.writerow([reldir, d])
    return root


@pytest.fixture
def synthetic_calib(tmp_path) -> Path:
    return write_calibration_folder(tmp_path / "calib")


@pytest.fixture(scope="session")
def mini_calib(mini_data):
    from tactile_slam.calibration.catalog import load_calibration_set

    return load_calibration_set(mini_data / "calibration", (H, W))


@pytest.fixture(scope="session")
def mini_labels(mini_calib):
    from tactile_slam.calibration.labels import label_presses

    return {lb.reldir: lb for lb in label_presses(mini_calib, MM_PER_PX, 2.0)}


@pytest.fixture(scope="session")
def reference_model(mini_data):
    from tactile_slam.calibration.model import load_model

    return load_model(mini_data / "reference_model" / "nnmodel.pth")[0]


@pytest.fixture(autouse=True)
def single_thread(one_thread):
    """The calibration MLPs are tiny: one thread is faster, and immune to a busy machine."""
