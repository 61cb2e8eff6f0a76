"""Contact mask and height zero level (method.md sections 3.1-3.2)."""

from __future__ import annotations

import torch

from tactile_slam.geometry.morphology import dilate, erode, fill_holes


def colour_distance(bgr: torch.Tensor, background: torch.Tensor) -> torch.Tensor:
    """Euclidean BGR distance to the background.

    Args:
        bgr: ``(B, H, W, 3)`` float or uint8.
        background: ``(H, W, 3)`` or ``(B, H, W, 3)`` float.

    Returns:
        ``(B, H, W)`` float32 distance in grey levels.
    """
    return torch.linalg.vector_norm(bgr.float() - background.float(), dim=-1)


def colour_mask(
    dist: torch.Tensor, threshold: float, dilate_size: int, erode_size: int, fill: bool = True
) -> torch.Tensor:
    """Colour rule: ``dist > threshold``, dilated then eroded (neutral borders).

    With ``fill`` (default; the public code does not) enclosed holes are filled: the
    flat bottom of a pressed ball has the background's colour although it is in
    contact. Real holes (an unpressed region inside a ring) are removed afterwards
    by the height rule of :func:`contact_mask`.

    ``(B, H, W)`` float -> ``(B, H, W)`` bool.
    """
    m = erode(dilate(dist > threshold, dilate_size), erode_size, border_is_contact=True)
    return fill_holes(m) if fill else m


def percentile(x: torch.Tensor, q: float) -> torch.Tensor:
    """Per-row percentile with linear interpolation (numpy's default).

    ``(B, N)`` -> ``(B,)``; ``q`` in [0, 100]. Two ``kthvalue`` selections instead of
    a full sort.
    """
    n = x.shape[1]
    pos = q / 100.0 * (n - 1)
    lo = int(pos)
    hi = min(lo + 1, n - 1)
    v_lo = torch.kthvalue(x, lo + 1, dim=1).values
    if hi == lo:
        return v_lo
    v_hi = torch.kthvalue(x, hi + 1, dim=1).values
    return v_lo + (pos - lo) * (v_hi - v_lo)


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
    enough = free.sum(dim=1) >= min_fraction * flat.shape[1]
    median = torch.where(free, flat, torch.nan).nanmedian(dim=1).values
    level = torch.where(enough, median, percentile(flat, 85.0))
    return height - level[:, None, None]


def contact_mask(
    height: torch.Tensor,
    colour: torch.Tensor | None,
    height_threshold_px: float,
    percentile_q: float,
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
    p = percentile(height.reshape(b, -1), percentile_q)
    raw = height < (p - height_threshold_px)[:, None, None]
    if colour is not None:
        raw = raw & colour
    return raw, erode(raw, final_erode, border_is_contact=False)
