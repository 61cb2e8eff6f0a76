"""Binary morphology on ``(B, H, W)`` bool tensors with explicit border semantics.

OpenCV treats out-of-image pixels as neutral for dilate/erode; the final contact
erosion of method.md section 3.2 treats them as non-contact. Both are provided.

On CPU the work goes to OpenCV (one call per image, zero-copy, ~100x faster than
torch's CPU max-pooling); on other devices it is a separable max-pool in torch. The
two backends give identical results (tested). The bounding box of a mask and a window
around such a box (:func:`mask_bounds`, :func:`window_around`) are here too: the stages
that work only near the contact share them.
"""

from __future__ import annotations

import cv2
import numpy as np
import torch
import torch.nn.functional as F


def as_weights(mask: torch.Tensor, dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """A bool mask as 0/1 values of ``dtype``, through a uint8 view (torch's direct
    bool-to-float conversion is ~6x slower on the CPU: 45 vs 7 us for a 320x240 mask).
    Any other dtype is converted directly. Same shape and device."""
    return (mask.view(torch.uint8) if mask.dtype == torch.bool else mask).to(dtype)


def _torch_dilate(mask: torch.Tensor, size: int, pad_value: float) -> torch.Tensor:
    x = as_weights(mask).unsqueeze(1)
    p0, p1 = size // 2, size - 1 - size // 2
    x = F.pad(x, (p0, p1, p0, p1), value=pad_value)
    x = F.max_pool2d(F.max_pool2d(x, (1, size), stride=1), (size, 1), stride=1)
    return x.squeeze(1) > 0.5


def _cv2_morph(mask: torch.Tensor, size: int, op: int, border_value: int | None) -> torch.Tensor:
    kernel = np.ones((size, size), np.uint8)
    src = mask.to(torch.uint8).numpy()
    out = np.empty_like(src)
    anchor = (size // 2, size // 2)
    for i in range(src.shape[0]):
        if border_value is None:
            cv2.morphologyEx(src[i], op, kernel, dst=out[i], anchor=anchor)
        else:
            cv2.morphologyEx(src[i], op, kernel, dst=out[i], anchor=anchor,
                             borderType=cv2.BORDER_CONSTANT, borderValue=border_value)
    return torch.from_numpy(out).bool()


def dilate(mask: torch.Tensor, size: int, backend: str = "auto") -> torch.Tensor:
    """Square dilation, out-of-image pixels neutral. ``(B, H, W)`` bool -> same.

    ``backend``: ``"auto"`` (OpenCV on CPU, torch elsewhere), ``"torch"`` or ``"cv2"``.
    """
    if size <= 1:
        return mask
    if use_cv2(mask, backend):
        return _cv2_morph(mask, size, cv2.MORPH_DILATE, None)
    return _torch_dilate(mask, size, 0.0)


def erode(mask: torch.Tensor, size: int, border_is_contact: bool = True, backend: str = "auto") -> torch.Tensor:
    """Square erosion. ``border_is_contact=True`` is OpenCV's neutral border;
    ``False`` treats out-of-image pixels as non-contact. ``(B, H, W)`` bool -> same."""
    if size <= 1:
        return mask
    if use_cv2(mask, backend):
        return _cv2_morph(mask, size, cv2.MORPH_ERODE, None if border_is_contact else 0)
    return ~_torch_dilate(~mask, size, 0.0 if border_is_contact else 1.0)


def use_cv2(mask: torch.Tensor, backend: str) -> bool:
    """Whether a ``backend`` setting (``"auto"``, ``"torch"`` or ``"cv2"``) picks OpenCV for
    ``mask``: ``"auto"`` does on the CPU."""
    if backend not in ("auto", "torch", "cv2"):
        raise ValueError(f"backend must be 'auto', 'torch' or 'cv2', got {backend!r}")
    if backend == "auto":
        return mask.device.type == "cpu"
    return backend == "cv2"


def fill_holes(mask: torch.Tensor, backend: str = "auto") -> torch.Tensor:
    """Fill regions of ``False`` not connected to the image border (4-connectivity).

    ``(B, H, W)`` bool -> same. On CPU one OpenCV flood fill per image; elsewhere a
    geodesic reconstruction of the border-connected background by repeated 3x3
    cross dilation until it stops changing.
    """
    if use_cv2(mask, backend):
        src = mask.to(torch.uint8).numpy()
        out = np.empty_like(src)
        for i in range(src.shape[0]):
            pad = np.pad(src[i], 1, constant_values=0)
            ff = pad.copy()
            cv2.floodFill(ff, np.zeros((pad.shape[0] + 2, pad.shape[1] + 2), np.uint8), (0, 0), 2, flags=4)
            out[i] = (ff[1:-1, 1:-1] != 2)
        return torch.from_numpy(out).bool()
    free = ~mask
    outside = torch.zeros_like(mask)
    outside[:, 0, :] = free[:, 0, :]
    outside[:, -1, :] = free[:, -1, :]
    outside[:, :, 0] |= free[:, :, 0]
    outside[:, :, -1] |= free[:, :, -1]
    cross = torch.tensor([[0, 1, 0], [1, 1, 1], [0, 1, 0]], dtype=torch.float32, device=mask.device)[None, None]
    while True:
        grown = (F.conv2d(as_weights(outside).unsqueeze(1), cross, padding=1).squeeze(1) > 0) & free
        if torch.equal(grown, outside):
            return ~outside
        outside = grown


def mask_bounds(mask: torch.Tensor) -> tuple[int, int, int, int] | None:
    """Bounding box ``(r0, r1, c0, c1)`` (half-open) of a ``(H, W)`` bool mask, or ``None``."""
    rows = torch.nonzero(mask.any(1)).flatten()
    if rows.numel() == 0:
        return None
    cols = torch.nonzero(mask.any(0)).flatten()
    return int(rows[0]), int(rows[-1]) + 1, int(cols[0]), int(cols[-1]) + 1


def window_around(bounds: tuple[int, int, int, int], margin: int, shape: tuple[int, int]) -> tuple[slice, slice]:
    """Rows and columns within ``margin`` pixels of inclusive ``bounds`` ``(r0, r1, c0, c1)``
    (e.g. :func:`~tactile_slam.geometry.frame.contact_bounds`), clipped to an image of
    ``shape`` ``(H, W)``."""
    r0, r1, c0, c1 = bounds
    h, w = shape
    return slice(max(r0 - margin, 0), min(r1 + margin + 1, h)), slice(max(c0 - margin, 0), min(c1 + margin + 1, w))
