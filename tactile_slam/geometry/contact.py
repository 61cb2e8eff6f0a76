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
        ``(B, H, W)`` float32 distance in grey levels (elementwise, in place on one
        temporary: a norm over the last axis of 3 is a slow reduction on the CPU, and
        each full-size temporary costs about as much as the arithmetic).
    """
    d = (bgr.float() - background.float()).square_()
    return (d[..., 0] + d[..., 1]).add_(d[..., 2]).sqrt_()


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


def order_statistic(x: torch.Tensor, k: int) -> torch.Tensor:
    """The ``k``-th smallest value (0-based) of each row: ``(B, N)`` -> ``(B,)``, with
    ``0 <= k < N``.

    Exact selection by ``torch.kthvalue`` on every device, and each value is gathered
    from ``x``, so gradients reach the selected entry. Which CPU selection is faster
    depends on the CPU: on 320x240 height maps numpy's introselect took 0.12-0.19 ms
    against 0.30-0.55 ms on the Intel Xeon VM (2026-11-27), but 0.76-0.98 ms against
    0.35-0.43 ms on the AMD EPYC VM (2026-11-29, numpy 2.4.6; docs/benchmarks.md).
    ``torch.kthvalue`` has the smaller worst case, and its version is pinned.
    """
    if x.ndim != 2 or not 0 <= k < x.shape[1]:
        raise ValueError(f"order_statistic: need (B, N) rows and 0 <= k < N, got shape {tuple(x.shape)} and k = {k}")
    idx = torch.kthvalue(x, k + 1, dim=1).indices[:, None]
    return torch.gather(x, 1, idx)[:, 0]


def percentile(x: torch.Tensor, q: float) -> torch.Tensor:
    """Per-row percentile with linear interpolation (numpy's default).

    ``(B, N)`` -> ``(B,)``; ``q`` in [0, 100]. One selection (:func:`order_statistic`)
    instead of a full sort; the next order statistic is the selected value again where
    it repeats, else the smallest value above it.
    """
    n = x.shape[1]
    pos = q / 100.0 * (n - 1)
    lo = int(pos)
    v_lo = order_statistic(x, lo)
    if lo + 1 >= n:
        return v_lo
    below = x <= v_lo[:, None]
    above = torch.where(below, torch.inf, x).amin(dim=1)
    v_hi = torch.where(below.sum(dim=1) >= lo + 2, v_lo, above)
    return v_lo + (pos - lo) * (v_hi - v_lo)


GEL_MIN_FRACTION = 0.05
"""The fraction of an image that must show undeformed gel for its heights to have a known zero."""


def gel_visible(changed: torch.Tensor, min_fraction: float = GEL_MIN_FRACTION) -> torch.Tensor:
    """Whether enough undeformed gel is in view to fix the height zero (and so the press
    depth): ``(B, H, W)`` bool ``changed`` -> ``(B,)`` bool, at least ``min_fraction`` of
    the pixels outside it. An object that covers the whole gel (a face larger than the
    sensor) leaves none: its depth is not observable from the slopes."""
    b = changed.shape[0]
    return _enough_gel((~changed.reshape(b, -1)).sum(dim=1), changed[0].numel(), min_fraction)


def _enough_gel(free_px: torch.Tensor, n_px: int, min_fraction: float) -> torch.Tensor:
    """``(B,)`` bool: ``free_px`` ``(B,)`` undeformed pixels of ``n_px`` are enough."""
    return free_px >= min_fraction * n_px


def zero_level(height: torch.Tensor, changed: torch.Tensor, min_fraction: float = GEL_MIN_FRACTION) -> torch.Tensor:
    """Shift heights so the undeformed gel is at 0.

    Subtracts the median of ``height`` over pixels outside ``changed`` (the dilated
    colour mask); where fewer than ``min_fraction`` of the pixels remain
    (:func:`gel_visible`), subtracts the 85th percentile instead: a guess, since the gel's
    own level is not in view.

    Args:
        height: ``(B, H, W)`` px.
        changed: ``(B, H, W)`` bool, pixels that differ from the background.

    Returns:
        ``(B, H, W)`` height with the gel at zero.
    """
    b = height.shape[0]
    flat = height.reshape(b, -1)
    free = ~changed.reshape(b, -1)
    free_px = free.sum(dim=1)
    counts, visible = free_px.tolist(), _enough_gel(free_px, flat.shape[1], min_fraction).tolist()
    rest = torch.where(free, flat, torch.inf)  # the lower median of the free pixels comes first
    level = []
    for i, m in enumerate(counts):
        if visible[i]:
            level.append(order_statistic(rest[i:i + 1], (m - 1) // 2)[0])
        else:
            level.append(percentile(flat[i:i + 1], 85.0)[0])
    return height - torch.stack(level)[:, None, None]


def contact_mask(
    height: torch.Tensor,
    colour: torch.Tensor | None,
    height_threshold_px: float,
    percentile_q: float,
    final_erode: int,
    fraction: float | None = None,
    floor_px: float = 0.0,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Contact rule: colour AND depth below the P85 level, then a final erosion whose
    out-of-image pixels count as non-contact.

    The depth test is ``P85(h) - h > t``. With ``fraction`` ``None`` (the public SDK's
    rule), or without a colour mask, ``t = height_threshold_px``. With a fraction and a
    colour mask, ``t = min(height_threshold_px, max(fraction * D, floor_px))``, ``D``
    being the frame's deepest point inside the colour mask: a deep press keeps the fixed
    threshold, while a touch not much deeper than it keeps the part deeper than
    ``fraction`` of its depth instead of vanishing (at ``fraction = 0.5``, where an
    elastic layer pressed by a sphere leaves the indenter: the surface at a Hertzian
    contact's edge sits at half the indentation).

    Args:
        height: ``(B, H, W)`` px.
        colour: ``(B, H, W)`` bool colour mask, or ``None`` (height rule only, for
            gradient-level input).
        height_threshold_px: the fixed threshold (the cap of the relative one).
        fraction, floor_px: the relative threshold's fraction of the deepest point and
            its lower bound; ``fraction=None`` keeps the fixed threshold.

    Returns:
        ``(raw, eroded)`` masks, each ``(B, H, W)`` bool.
    """
    b = height.shape[0]
    p = percentile(height.reshape(b, -1), percentile_q)
    depth = p[:, None, None] - height
    t = torch.full_like(p, height_threshold_px)
    if fraction is not None and colour is not None:  # height alone (gradient input) keeps the fixed rule
        deepest = torch.where(colour, depth, torch.zeros_like(depth)).reshape(b, -1).amax(dim=1)
        t = torch.minimum(t, (fraction * deepest).clamp(min=floor_px))
    raw = depth > t[:, None, None]
    if colour is not None:
        raw = raw & colour
    return raw, erode(raw, final_erode, border_is_contact=False)
