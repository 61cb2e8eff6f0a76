"""Analytic test surfaces (heights in px) and their exact or central-difference gradients."""

from __future__ import annotations

import math

import torch

H, W = 240, 320


def grid(dtype=torch.float64):
    r = torch.arange(H, dtype=dtype)[:, None] - (H - 1) / 2
    c = torch.arange(W, dtype=dtype)[None, :] - (W - 1) / 2
    return r.expand(H, W), c.expand(H, W)


def gaussian_dent(depth=10.0, sigma=20.0, dtype=torch.float64):
    r, c = grid(dtype)
    return -depth * torch.exp(-(r**2 + c**2) / (2 * sigma**2))


def spherical_cap(radius=49.76, depth=12.0, cr=0.0, cc=0.0, dtype=torch.float64):
    """A ball of ``radius`` px pressed ``depth`` px into a flat gel at (cr, cc)."""
    r, c = grid(dtype)
    d2 = (r - cr) ** 2 + (c - cc) ** 2
    z = torch.sqrt(torch.clamp(radius**2 - d2, min=0.0)) - (radius - depth)
    return -torch.clamp(z, min=0.0)


def sinusoid(amp=3.0, period=40.0, dtype=torch.float64):
    r, c = grid(dtype)
    return amp * torch.sin(2 * math.pi * c / period) * torch.cos(2 * math.pi * r / (1.3 * period))


def central_gradients(h: torch.Tensor) -> torch.Tensor:
    """``(H, W)`` -> ``(1, H, W, 2)`` by numpy-style central differences."""
    gy, gx = torch.gradient(h, dim=(0, 1))
    return torch.stack([gx, gy], dim=-1)[None]
