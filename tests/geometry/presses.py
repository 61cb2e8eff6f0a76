"""Real GelSight Mini presses with an independent estimate of the ball's contact disc.

The disc is estimated from the gradient field alone: on a sphere the slope vector at
pixel p points away from the centre c, so ``(p - c) x g = 0`` gives c by linear
least squares, and the contact radius is where the radial slope profile stops
following the sphere's ``r / sqrt(R^2 - r^2)``. Nothing here uses the contact mask.
"""

from __future__ import annotations

import csv
from pathlib import Path

import cv2
import numpy as np
import torch

MM_PER_PX = 0.0634


def catalog(root: Path) -> list[tuple[str, float]]:
    with open(root / "calibration" / "catalog.csv") as f:
        rows = list(csv.reader(f))[1:]
    return [(r[0], float(r[1])) for r in rows]


def load_press(root: Path, reldir: str) -> torch.Tensor:
    img = cv2.imread(str(root / "calibration" / reldir / "gelsight.png"))
    return torch.from_numpy(img)


def load_background(root: Path) -> torch.Tensor:
    return torch.from_numpy(cv2.imread(str(root / "calibration" / "background.png"))).float()


def fit_disc(gradients: np.ndarray, diameter_mm: float) -> tuple[float, float, float]:
    """``(H, W, 2)`` slopes -> (cx, cy, contact radius) in px."""
    gx, gy = gradients[..., 0], gradients[..., 1]
    mag = np.hypot(gx, gy)
    ys, xs = np.nonzero(mag > 0.1)
    a = np.stack([gy[ys, xs], -gx[ys, xs]], axis=1)
    b = xs * gy[ys, xs] - ys * gx[ys, xs]
    w = mag[ys, xs]
    (cx, cy), *_ = np.linalg.lstsq(a * w[:, None], b * w, rcond=None)
    big_r = diameter_mm / MM_PER_PX / 2
    h, w_ = mag.shape
    yy, xx = np.mgrid[0:h, 0:w_]
    rr = np.hypot(xx - cx, yy - cy)
    radius = 0.0
    for r in np.arange(3, big_r * 0.95, 1.0):
        ring = (rr >= r - 0.5) & (rr < r + 0.5)
        if ring.sum() < 10:
            break
        expected = r / np.sqrt(big_r**2 - r**2)
        if np.median(mag[ring]) < 0.7 * expected:
            break
        radius = r
    return float(cx), float(cy), radius
