"""Helpers for the I/O tests: synthetic sensor-like frames and small recordings."""

from __future__ import annotations

import numpy as np
import pytest


def _gel_frames(n: int, shape: tuple[int, int] = (240, 320), noise: float = 1.0, seed: int = 0) -> np.ndarray:
    """``(n, H, W, 3)`` uint8 frames: a smooth, sensor-like colour field plus Gaussian noise."""
    h, w = shape
    yy, xx = np.mgrid[:h, :w].astype(np.float64)
    base = np.stack([100 + 50 * np.sin(xx / 30), 120 + 40 * np.cos(yy / 25), 90 + 0.2 * xx], axis=-1)
    rng = np.random.default_rng(seed)
    return np.clip(np.round(base + rng.normal(0.0, noise, (n, h, w, 3))), 0, 255).astype(np.uint8)


def _press(frames: np.ndarray, i: int, center: tuple[int, int], radius: int, amplitude: float) -> np.ndarray:
    """Copy of ``frames`` with a disc of colour change ``amplitude`` pressed into frame ``i``."""
    out = frames.astype(np.float64)
    h, w = frames.shape[1:3]
    yy, xx = np.mgrid[:h, :w]
    disc = (yy - center[0]) ** 2 + (xx - center[1]) ** 2 < radius**2
    out[i][disc] += amplitude
    return np.clip(out, 0, 255).astype(np.uint8)


@pytest.fixture
def gel_frames():
    """The synthetic frame generator ``gel_frames(n, shape, noise, seed)``."""
    return _gel_frames


@pytest.fixture
def press():
    """``press(frames, i, center, radius, amplitude)``: add a contact disc to frame ``i``."""
    return _press


@pytest.fixture
def frames() -> np.ndarray:
    """14 small noisy frames, 48x64."""
    return _gel_frames(14, (48, 64), seed=3)
