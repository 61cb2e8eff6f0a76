"""Reference sample selection for NormalFlow (method.md section 4.2).

Every rule returns padded row-major pixel indices ``(B, K)`` and a validity mask, so
references with different contact sizes share one batch.
"""

from __future__ import annotations

import numpy as np
import torch

from tactile_slam.config import SAMPLE_SELECTIONS as SELECTIONS
from tactile_slam.registration.result import RegistrationError


def flat_nonzero(mask: torch.Tensor) -> torch.Tensor:
    """Indices of the true entries of a bool tensor, flattened row-major. On the CPU
    numpy's one-dimensional scan, 2-5x faster than torch's ``nonzero`` on contact and
    sample masks. ``(...)`` -> ``(M,)`` int64."""
    if mask.device.type != "cpu":
        return mask.reshape(-1).nonzero()[:, 0]
    return torch.from_numpy(np.flatnonzero(mask.numpy()))


def nonzero_2d(mask: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Row and column indices of the true entries of a ``(B, N)`` bool mask, row-major
    (as ``mask.nonzero(as_tuple=True)``). ``(B, N)`` -> ``(rows (M,), cols (M,))`` int64."""
    flat = flat_nonzero(mask)
    n = mask.shape[1]
    return flat // n, flat % n


def mask_to_indices(mask: torch.Tensor, k: int | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Row-major indices of the true entries of each row, padded.

    Args:
        mask: ``(B, N)`` bool.
        k: number of columns (default: the largest row count, at least 1); rows with
            more true entries keep their first ``k``.

    Returns:
        ``(idx (B, K) int64, valid (B, K) bool)``; padding has index 0, valid False.
    """
    b, n = mask.shape
    dev = mask.device
    if b == 1 and k is None:  # one row: a plain nonzero (the general path costs ~2.4x more)
        idx = flat_nonzero(mask)
        if len(idx) == 0:
            return torch.zeros((1, 1), dtype=torch.int64, device=dev), torch.zeros((1, 1), dtype=torch.bool, device=dev)
        return idx[None], torch.ones((1, len(idx)), dtype=torch.bool, device=dev)
    rows, cols = nonzero_2d(mask)  # row-major order
    count = torch.bincount(rows, minlength=b)  # a bool sum would widen the whole mask to int64
    longest = int(count.max()) if b else 0
    if k is None:
        k = max(longest, 1)
    pos = torch.arange(len(rows), device=dev) - (count.cumsum(0) - count)[rows]
    if longest > k:  # rows longer than k keep their first k
        keep = pos < k
        rows, cols, pos = rows[keep], cols[keep], pos[keep]
    idx = torch.zeros(b * k, dtype=torch.int64, device=dev)
    idx[rows * k + pos] = cols
    valid = torch.arange(k, device=dev)[None, :] < count.clamp(max=k)[:, None]
    return idx.view(b, k), valid


def top_k_mask(score: torch.Tensor, k: int) -> torch.Tensor:
    """Exactly ``min(k, #(score >= 0))`` largest non-negative entries per row, ties
    broken by the lower index. Negative scores are never selected.

    ``(B, N)`` -> ``(B, N)`` bool.
    """
    n = score.shape[1]
    if k >= n:
        return score >= 0
    kth = torch.topk(score, k, dim=1, sorted=False).values.min(dim=1, keepdim=True).values
    above = score > kth
    tie = score == kth
    need = k - above.sum(dim=1, keepdim=True)
    if bool((tie.sum(dim=1, keepdim=True) > need).any()):  # keep the first ties only
        tie = tie & (tie.cumsum(dim=1) <= need)
    chosen = above | tie
    return torch.where(kth >= 0, chosen, score >= 0)


def top_k_indices(score: torch.Tensor, k: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Row-major indices of the :func:`top_k_mask` selection, padded like
    :func:`mask_to_indices` (to the largest row count). One ``topk``, its members
    marked in a mask and read back in row-major order (cheaper than sorting them);
    rows where ``topk`` took a different member of a tie at the k-th value fall back
    to :func:`top_k_mask`.

    ``(B, N)`` -> ``(idx (B, K) int64, valid (B, K) bool)``.
    """
    n = score.shape[1]
    vals, ids = torch.topk(score, min(k, n), dim=1, sorted=False)
    kth = vals.amin(1, keepdim=True)
    ties = (score == kth).sum(1, dtype=torch.int32)  # int32: no int64 copy of the mask
    unfair = (ties > (vals == kth).sum(1, dtype=torch.int32)) & (kth[:, 0] >= 0)
    if bool(unfair.any()):
        return mask_to_indices(top_k_mask(score, k))
    return mask_to_indices(torch.zeros_like(score, dtype=torch.bool).scatter_(1, ids, vals >= 0))


def spread_top_k(score: torch.Tensor, pixel: torch.Tensor, inside: torch.Tensor, width: int, cell_px: int,
                 k: int) -> tuple[torch.Tensor, torch.Tensor]:
    """The ``k`` highest scores spread over the contact: the image is cut into
    ``cell_px``-square cells, each candidate is ranked within its cell by its score in
    65,536 levels of the frame's highest (ties by index), and the ``k`` with the smallest
    within-cell fraction ``(rank + 0.5) / count`` are taken (ties: the higher score, then
    the lower index). Each cell thus gets a share of ``k`` proportional to its number of
    candidates, filled by its own best scores. All candidates are taken when there are at
    most ``k``.

    On the CPU each frame is ranked by numpy (:func:`_spread_row`; radix sorts, 3x
    the batched torch ops per frame), elsewhere by :func:`_spread_batch`.

    Args:
        score: ``(B, M)`` non-negative scores of the candidates.
        pixel: ``(B, M)`` row-major pixel indices of the candidates (image width ``width``),
            the valid ones first in each row (as :func:`mask_to_indices` pads).
        inside: ``(B, M)`` bool, False for padding.

    Returns:
        ``(pos (B, K) int64 positions into the candidates, valid (B, K) bool)``, in
        candidate order (as :func:`top_k_indices`).
    """
    b, m = pixel.shape
    if m <= k:  # every candidate is taken
        return torch.arange(m, device=pixel.device).expand(b, m).clone(), inside.clone()
    if pixel.device.type != "cpu":
        return _spread_batch(score, pixel, inside, width, cell_px, k)
    rows = [_spread_row(score[i, :n].numpy(), pixel[i, :n].numpy(), width, cell_px, k)
            for i, n in enumerate(inside.sum(1).tolist())]
    lengths = torch.tensor([len(r) for r in rows])
    pos = np.zeros((b, max(int(lengths.max()), 1)), dtype=np.int64)
    for i, r in enumerate(rows):
        pos[i, :len(r)] = r
    return torch.from_numpy(pos), torch.arange(pos.shape[1])[None, :] < lengths[:, None]


def _cells(pixel, width: int, cell_px: int):
    """Cell of each row-major pixel index (numpy or torch integers, same shape)."""
    row = pixel // width
    return (row // cell_px) * -(-width // cell_px) + (pixel - row * width) // cell_px


def _spread_row(score: np.ndarray, pixel: np.ndarray, width: int, cell_px: int, k: int) -> np.ndarray:
    """:func:`spread_top_k` of one frame's ``(M,)`` valid candidates -> ``(min(M, k),)``
    sorted positions."""
    m = len(score)
    if m <= k:
        return np.arange(m)
    cell = _cells(pixel.astype(np.int32), width, cell_px)  # int32 division: half the time of int64's
    top = score.max()
    level = 65535 - np.clip(np.floor(score / (top if top > 0 else 1.0) * 65535), 0, 65535)
    # stable by cell, then level, then position: numpy radix-sorts 16-bit keys
    order = np.lexsort((level.astype(np.uint16), cell.astype(np.int16 if cell.max() < 2**15 else np.int32)))
    count = np.bincount(cell)
    start = np.cumsum(count) - count
    rank = np.empty(m, dtype=np.int64)
    rank[order] = np.arange(m) - start[cell[order]]
    key = 1.0 - (rank + 0.5) / count[cell] + 1e-9 * score.astype(np.float64)
    kth = np.partition(key, m - k)[m - k]
    chosen = key > kth
    need = k - int(chosen.sum())
    if need > 0:  # ties at the k-th key: the lower positions
        chosen[np.flatnonzero(key == kth)[:need]] = True
    return np.flatnonzero(chosen)


def _spread_batch(score: torch.Tensor, pixel: torch.Tensor, inside: torch.Tensor, width: int, cell_px: int,
                  k: int) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`spread_top_k` as batched torch ops (for accelerators)."""
    m = pixel.shape[1]
    cell = _cells(pixel.int(), width, cell_px).long()
    pad = int(cell.max()) + 1
    cell = torch.where(inside, cell, pad)  # padding: a cell of its own, last
    top = torch.where(inside, score, 0.0).amax(1, keepdim=True)
    level = 65535 - (score / torch.where(top > 0, top, 1.0) * 65535).floor().clamp(0, 65535).long()  # descending
    order = torch.sort(cell * 65536 + level, dim=1, stable=True).indices
    count = torch.zeros((pixel.shape[0], pad + 1), dtype=torch.int64, device=pixel.device).scatter_add_(
        1, cell, torch.ones_like(cell))
    start = count.cumsum(1) - count
    rank_sorted = torch.arange(m, device=pixel.device) - start.gather(1, cell.gather(1, order))
    rank = torch.empty_like(rank_sorted).scatter_(1, order, rank_sorted)
    key = torch.where(inside, 1.0 - (rank + 0.5) / count.gather(1, cell) + 1e-9 * score.double(), -1.0)
    return top_k_indices(key, k)


def within_slope(normals: torch.Tensor, contact: torch.Tensor, max_slope: float,
                 min_fraction: float = 0.25) -> torch.Tensor:
    """The contact pixels whose surface slope ``|n_xy| / |n_z|`` is at most ``max_slope``
    (NaN counts as steeper): the gel's smoothing bends steep slopes of tilted touches, and
    where the slopes were decoded from an image, steeper ones lie beyond what the
    calibration presses showed the decoder, which flattens them (docs/registration.md,
    "Steep pixels through the gel", "Steep pixels from video"). A frame keeps its whole
    contact when fewer than ``min_fraction`` of its contact pixels are that flat: a touch
    that is mostly steep is registered on its flattened slopes rather than on a sliver.
    Only the contact pixels are read.

    ``(B, H, W, 3)`` normals, ``(B, H, W)`` bool contact -> ``(B, H, W)`` bool.
    """
    b = contact.shape[0]
    idx = flat_nonzero(contact)  # only the contact pixels are tested: a few thousand of the image's
    n = normals.reshape(-1, 3).index_select(0, idx).unbind(-1)
    # squared sides: no square root; NaN counts as steep
    steep = ~(n[0] * n[0] + n[1] * n[1] <= (max_slope * max_slope) * (n[2] * n[2]))
    frame = idx // contact[0].numel()
    total = torch.bincount(frame, minlength=b)
    enough = total - torch.bincount(frame[steep], minlength=b) >= min_fraction * total
    out = contact.clone()
    out.view(-1)[idx[steep & enough[frame]]] = False
    return out


def _check_scores(score: torch.Tensor) -> None:
    """NaN would silently drop a pixel from the ranking (and Inf take its place): either
    is an input error."""
    if not bool(torch.isfinite(score.sum())):
        raise RegistrationError("reference curvature contains NaN or Inf at contact pixels")


def select_samples(
    curvature: torch.Tensor,
    contact: torch.Tensor,
    n_samples: int | None,
    rule: str = "spread",
    generator: torch.Generator | None = None,
    cell_px: int = 16,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Reference pixels NormalFlow optimises over.

    Rules:
        ``"spread"``: the ``n_samples`` contact pixels of highest |L| within
            ``cell_px``-square cells, each cell's share proportional to its contact
            pixels (:func:`spread_top_k`); all contact pixels when fewer;
            deterministic. On a large contact a global top-k gathers on a few features
            (an edge, the pips of a face) and can leave a motion weakly constrained
            (docs/registration.md, "Samples spread over the contact").
        ``"topk"``: the ``n_samples`` contact pixels of highest |L|, ties by row-major
            index (all contact pixels when fewer); deterministic (method.md 4.2).
        ``"threshold"``: the public GelSLAM rule: |L| >= (n-th largest |L| over the
            image) + 1e-6 (at most n - 1 samples; none when n pixels sit at the clip).
        ``"random"``: ``n_samples`` contact pixels drawn uniformly (old NormalFlow), one
            number per contact pixel from ``generator``.

    Args:
        curvature: ``(B, H, W)`` reference curvature L (zero outside contact).
        contact: ``(B, H, W)`` bool eroded contact mask.
        n_samples: sample count, ``None`` for every contact pixel.
        generator: CPU random generator for ``"random"``.

    Returns:
        ``(idx (B, K) int64 row-major pixel indices, valid (B, K) bool)``, row-major order.
    """
    if rule not in SELECTIONS:
        raise ValueError(f"sample selection must be one of {SELECTIONS}, got {rule!r}")
    b = curvature.shape[0]
    flat = curvature.reshape(b, -1)
    c = contact.reshape(b, -1)
    if n_samples is None:
        return mask_to_indices(c)
    if n_samples < 1:
        raise ValueError(f"n_samples must be >= 1 or None, got {n_samples}")
    if rule in ("topk", "spread"):  # over the contact pixels only (a few thousand of the image's pixels)
        pixel, inside = mask_to_indices(c)
        score = torch.where(inside, flat.gather(1, pixel).abs(), -1.0)
        _check_scores(score)
        if rule == "spread":
            pos, valid = spread_top_k(score.clamp_min(0.0), pixel, inside, curvature.shape[2], cell_px, n_samples)
        else:
            pos, valid = top_k_indices(score, n_samples)
        return pixel.gather(1, pos), valid
    if rule == "random":  # one draw per contact pixel, not per image pixel
        pixel, inside = mask_to_indices(c)
        r = torch.rand(pixel.shape, generator=generator, dtype=torch.float64).to(flat.device)
        pos, valid = top_k_indices(torch.where(inside, r, -1.0), n_samples)
        return pixel.gather(1, pos), valid
    a = flat.abs()
    _check_scores(a)  # this rule ranks the whole image
    k = min(n_samples, a.shape[1])
    tau = torch.topk(a, k, dim=1).values[:, -1:] + 1e-6
    return mask_to_indices(a >= tau)
