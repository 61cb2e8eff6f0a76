"""Normals and curvature from gradients (method.md sections 1.3 and 3.3)."""

from __future__ import annotations

import kornia
import torch

from tactile_slam.geometry.morphology import as_weights


def normals_from_gradients(gradients: torch.Tensor) -> torch.Tensor:
    """Gel-surface unit normals ``N = (-gx, -gy, 1) / |.|`` (toward the object).

    ``(B, H, W, 2)`` -> ``(B, H, W, 3)``. Elementwise (a norm over the last axis of 3 is a
    slow reduction on the CPU).
    """
    gx, gy = gradients[..., 0], gradients[..., 1]
    inv = torch.rsqrt(gx * gx + gy * gy + 1.0)
    return torch.stack([-gx * inv, -gy * inv, inv], dim=-1)


def _central_diff(f: torch.Tensor, dim: int) -> torch.Tensor:
    """Halved central differences, one-sided at the edges (numpy.gradient)."""
    return torch.gradient(f, dim=dim)[0]


def divergence(gradients: torch.Tensor) -> torch.Tensor:
    """``d gx/dx + d gy/dy`` by central differences. ``(B, H, W, 2)`` -> ``(B, H, W)``."""
    return _central_diff(gradients[..., 0], -1) + _central_diff(gradients[..., 1], -2)


def curvature(
    gradients: torch.Tensor,
    contact: torch.Tensor,
    ksize: int = 5,
    sigma: float = 1.1,
    clip: float = 0.7,
) -> torch.Tensor:
    """Curvature ``L``: divergence, Gaussian blur (reflect-101), zero outside contact,
    clipped to ``[-clip, clip]``.

    Args:
        gradients: ``(B, H, W, 2)``.
        contact: ``(B, H, W)`` bool, the eroded contact mask.

    Returns:
        ``(B, H, W)`` in 1/px.
    """
    div = divergence(gradients).unsqueeze(1)
    blurred = kornia.filters.gaussian_blur2d(div, (ksize, ksize), (sigma, sigma), border_type="reflect")
    lap = blurred.squeeze(1) * as_weights(contact, blurred.dtype)
    return lap.clamp(-clip, clip)
