"""Normals and curvature from gradients (method.md sections 1.3 and 3.3)."""

from __future__ import annotations

from functools import lru_cache

import kornia
import torch

from tactile_slam.config import min_image_px
from tactile_slam.geometry.morphology import as_weights, mask_bounds, window_around


def normals_from_gradients(gradients: torch.Tensor) -> torch.Tensor:
    """Gel-surface unit normals ``N = (-gx, -gy, 1) / |.|`` (toward the object).

    ``(B, H, W, 2)`` -> ``(B, H, W, 3)``. Elementwise (a norm over the last axis of 3 is a
    slow reduction on the CPU; the fewer full-size temporaries, the faster).
    """
    sq = gradients.square()
    inv = torch.rsqrt((sq[..., 0] + sq[..., 1]).add_(1.0))
    return torch.cat([gradients * -inv[..., None], inv[..., None]], dim=-1)


def _central_diff(f: torch.Tensor, dim: int) -> torch.Tensor:
    """Halved central differences, one-sided at the edges (numpy.gradient)."""
    return torch.gradient(f, dim=dim)[0]


def divergence(gradients: torch.Tensor) -> torch.Tensor:
    """``d gx/dx + d gy/dy`` by central differences. ``(B, H, W, 2)`` -> ``(B, H, W)``."""
    return _central_diff(gradients[..., 0], -1) + _central_diff(gradients[..., 1], -2)


@lru_cache(maxsize=8)
def gaussian_kernel(ksize: int, sigma: float, dtype: torch.dtype, device: str) -> torch.Tensor:
    """kornia's ``(1, ksize)`` Gaussian kernel, built once per setting: ``gaussian_blur2d``
    builds it (and checks sigma) on every call, about half of its time on a contact window
    (0.59 against 0.32 ms for a 130x170 window; the same values)."""
    sigma_t = torch.tensor([[sigma]], dtype=dtype, device=device)
    return kornia.filters.get_gaussian_kernel1d(ksize, sigma_t)


def curvature(
    gradients: torch.Tensor,
    contact: torch.Tensor,
    ksize: int = 5,
    sigma: float = 1.1,
    clip: float = 0.7,
) -> torch.Tensor:
    """Curvature ``L``: divergence, Gaussian blur (reflect-101), zero outside contact,
    clipped to ``[-clip, clip]``.

    Only a window around the batch's contact is computed: ``ksize // 2 + 1`` pixels
    beyond its bounding box, the blur's reach plus the divergence's, so every contact
    pixel reads what it would read in the full image (where the window meets the
    image border, the border rules are the full image's own). The result is the
    full-image computation's, at a fraction of its cost when contact is small.

    Args:
        gradients: ``(B, H, W, 2)``.
        contact: ``(B, H, W)`` bool, the eroded contact mask.

    Returns:
        ``(B, H, W)`` in 1/px.
    """
    return _blurred_in_contact(divergence, None, gradients, contact, ksize, sigma, clip)


def _blurred_in_contact(field, finish, gradients: torch.Tensor, contact: torch.Tensor, ksize: int, sigma: float,
                        clip: float) -> torch.Tensor:
    """``finish(blur(field(gradients)))`` (``finish`` None: the blurred field), zero outside
    contact and clipped, computed in the window around the batch's contact that every
    contact pixel's full-image value reads (``ksize // 2 + 1`` pixels: the blur's reach
    plus a central difference's), so a frame reads the same alone or in a batch, to the
    rounding of the dtype (float32 sums in another window order differ by ~1e-8).
    ``field``: ``(b, h, w, 2)`` -> ``(b, h, w)``."""
    h, w = gradients.shape[1:3]
    if min(h, w) < min_image_px(ksize):
        raise ValueError(f"a {h}x{w} image is too small for curvature with a {ksize}-px blur "
                         f"(at least {min_image_px(ksize)} px each way)")
    out = torch.zeros(gradients.shape[:3], dtype=gradients.dtype, device=gradients.device)
    box = mask_bounds(contact.any(0))  # of every frame's contact
    if box is None:
        return out
    r0, r1, c0, c1 = box
    rows, cols = window_around((r0, r1 - 1, c0, c1 - 1), ksize // 2 + 1, contact.shape[1:])
    raw = field(gradients[:, rows, cols]).unsqueeze(1)
    kernel = gaussian_kernel(ksize, sigma, raw.dtype, str(raw.device))
    blurred = kornia.filters.filter2d_separable(raw, kernel, kernel, border_type="reflect").squeeze(1)
    value = blurred if finish is None else finish(blurred)
    out[:, rows, cols] = (value * as_weights(contact[:, rows, cols], value.dtype)).clamp(-clip, clip)
    return out


def gaussian_curvature(
    gradients: torch.Tensor,
    contact: torch.Tensor,
    ksize: int = 5,
    sigma: float = 1.1,
    clip: float = 0.7,
) -> torch.Tensor:
    """Gaussian curvature as a Laplacian-like map: ``2 sign(K) sqrt(|K|)`` with ``K`` the
    blurred Hessian determinant of the height, ``g_xx g_yy - g_xy^2`` of the slopes (central
    differences, ``g_xy`` symmetrised; Gaussian blur as :func:`curvature`), zero outside
    contact, clipped to ``[-clip, clip]``.

    The Laplacian (:func:`curvature`) answers to lines (ribs, growth lines, print layers)
    as strongly as to bumps. ``K`` vanishes along a line, where one principal curvature is
    zero, and keeps bumps, pits, saddles, corners and crossings: places a keypoint detector
    can find again from another touch. ``2 sqrt(|K|)`` is the Laplacian a spherical bump
    of the same ``K`` has (``kappa_1 = kappa_2``), so the same ``clip`` and 8-bit scale
    serve both maps. Rotation invariant about the sensor axis, like the Laplacian. Computed
    in a window around the batch's contact, like :func:`curvature`.

    Args:
        gradients: ``(B, H, W, 2)``.
        contact: ``(B, H, W)`` bool.

    Returns:
        ``(B, H, W)`` in 1/px.
    """
    return _blurred_in_contact(hessian_determinant, lambda k: 2.0 * k.sign() * k.abs().sqrt(), gradients, contact,
                               ksize, sigma, clip)


def hessian_determinant(gradients: torch.Tensor) -> torch.Tensor:
    """``g_xx g_yy - g_xy^2`` of the slopes by central differences (``g_xy`` the mean of
    the two mixed derivatives). ``(B, H, W, 2)`` -> ``(B, H, W)``."""
    gx_y, gx_x = torch.gradient(gradients[..., 0], dim=(-2, -1))
    gy_y, gy_x = torch.gradient(gradients[..., 1], dim=(-2, -1))
    return gx_x * gy_y - (0.5 * (gx_y + gy_x)) ** 2
