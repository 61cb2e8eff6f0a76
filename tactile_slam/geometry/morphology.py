"""Binary morphology on ``(B, H, W)`` bool tensors with explicit border semantics.

OpenCV treats out-of-image pixels as neutral for dilate/erode; the final contact
erosion of method.md section 3.2 treats them as non-contact. Both are provided.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F


def dilate(mask: torch.Tensor, size: int) -> torch.Tensor:
    """Square dilation, out-of-image pixels neutral. ``(B, H, W)`` bool -> same."""
    if size <= 1:
        return mask
    x = mask.float().unsqueeze(1)
    p = size // 2
    x = F.max_pool2d(F.pad(x, (p, size - 1 - p, p, size - 1 - p), value=0.0), size, stride=1)
    return x.squeeze(1) > 0.5


def erode(mask: torch.Tensor, size: int, border_is_contact: bool = True) -> torch.Tensor:
    """Square erosion. ``border_is_contact=True`` is OpenCV's neutral border;
    ``False`` treats out-of-image pixels as non-contact. ``(B, H, W)`` bool -> same."""
    if size <= 1:
        return mask
    x = (~mask).float().unsqueeze(1)
    p = size // 2
    pad_value = 0.0 if border_is_contact else 1.0
    x = F.max_pool2d(F.pad(x, (p, size - 1 - p, p, size - 1 - p), value=pad_value), size, stride=1)
    return x.squeeze(1) < 0.5
