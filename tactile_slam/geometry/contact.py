"""Contact mask and height zero level (method.md sections 3.1-3.2)."""

from __future__ import annotations

import torch

from tactile_slam.geometry.morphology import dilate, erode


def colour_distance(bgr: torch.Tensor, background: torch.Tensor) -> torch.Tensor:
    """Euclidean BGR distance to the background.

    Args:
        bgr: ``(B, H, W, 3)`` float or uint8.
        background: ``(H, W, 3)`` or ``(B, H, W, 3)`` float.

    Returns:
        ``(B, H, W)`` float32 distance in grey levels.
    """
    return torch.linalg.vector_norm(bgr.float() - background.float(), dim=-1)


def colour_mask(dist: torch.Tensor, threshold: float, dilate_size: int, erode_size: int) -> torch.Tensor:
    """Colour rule: ``dist > threshold``, dilated then eroded (neutral borders).
    ``(B, H, W)`` float -> ``(B, H, W)`` bool."""
    return erode(dilate(dist > threshold, dilate_size), erode_size, border_is_contact=True)


def zero_level(height: torch.Tensor, changed: torch.Tensor, min_fraction: float = 0.05) -> torch.Tensor:
    """Shift heights so the undeformed gel is at 0.

    Subtracts the median of ``height`` over pixels outside ``changed`` (the dilated
    colour mask); where fewer than ``min_fraction`` of the pixels remain, subtracts the
    85th percentile instead.

    Args:
        height: ``(B, H, W)`` px.
        changed: ``(B, H, W)`` bool, pixels that differ from the background.

    Returns:
        ``(B, H, W)`` height with the gel at zero.
    """
    b = height.shape[0]
    flat = height.reshape(b, -1)
    free = ~changed.reshape(b, -1)
    n_free = free.sum(dim=1)
    # median over free pixels: push non-free pixels to +inf and take the k-th value
    big = torch.finfo(height.dtype).max
    masked = torch.where(free, flat, torch.full_like(flat, big))
    k = ((n_free - 1).clamp_min(0) // 2)
    sorted_vals = masked.sort(dim=1).values
    median = sorted_vals.gather(1, k[:, None]).squeeze(1)
    p85 = torch.quantile(flat, 0.85, dim=1)
    enough = n_free >= min_fraction * flat.shape[1]
    level = torch.where(enough, median, p85)
    return height - level[:, None, None]


def contact_mask(
    height: torch.Tensor,
    colour: torch.Tensor | None,
    height_threshold_px: float,
    percentile: float,
    final_erode: int,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Contact rule: colour AND height below P85 - threshold, then a final erosion
    whose out-of-image pixels count as non-contact.

    Args:
        height: ``(B, H, W)`` px.
        colour: ``(B, H, W)`` bool colour mask, or ``None`` (height rule only, for
            gradient-level input).

    Returns:
        ``(raw, eroded)`` masks, each ``(B, H, W)`` bool.
    """
    b = height.shape[0]
    p = torch.quantile(height.reshape(b, -1), percentile / 100.0, dim=1)
    raw = height < (p - height_threshold_px)[:, None, None]
    if colour is not None:
        raw = raw & colour
    return raw, erode(raw, final_erode, border_is_contact=False)
