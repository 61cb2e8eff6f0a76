"""Keypoints and descriptors for loop detection (method.md section 6.2).

Curvature is invariant to rigid motion of the object, so SIFT on the curvature map of
a keyframe finds the same surface features from any pose. The map is turned into an
8-bit image ``g = trunc((L + clip) / (2 clip) * 255)`` (``L = 0`` maps to 127), cropped
to the bounding box of the eroded contact, and described by SIFT; keypoints survive
only where a further erosion of the contact (out-of-image pixels count as non-contact)
is true at their rounded coordinates, so no keypoint sits on the contact edge, whose
shape is not a property of the surface.

Two SIFT backends:

* ``"opencv"`` (default): ``cv2.SIFT`` with ``contrastThreshold`` 0.02, 3 octave
  layers and ``edgeThreshold`` 10, as in the public code. Low-contrast curvature images
  need the low threshold.
* ``"kornia"``: ``kornia.feature.SIFTFeatureScaleSpace`` (DoG scale space, refined
  extrema, SIFT descriptors), keeping the ``max_features`` strongest responses above the
  same contrast threshold. Device-agnostic but slower on CPU (see docs/loops.md).

:func:`image_features` is the GS-ImageSIFT ablation: the same detector on the raw grey
GelSight image inside the contact.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import cv2
import numpy as np
import torch

from tactile_slam.config import SIFT_BACKENDS
from tactile_slam.geometry.curvature import gaussian_curvature
from tactile_slam.geometry.morphology import erode, mask_bounds, window_around


class FeatureError(ValueError):
    """Unusable input to feature extraction (wrong shape or dtype, NaN, unknown backend)."""


@dataclass
class Features:
    """Keypoints and descriptors of one keyframe.

    Attributes:
        keypoints: ``(N, 2)`` float32 pixel coordinates ``(x = column, y = row)``.
        descriptors: ``(N, 128)`` float32 SIFT descriptors (L2 matching).
    """

    keypoints: torch.Tensor
    descriptors: torch.Tensor

    def __len__(self) -> int:
        return self.keypoints.shape[0]

    @staticmethod
    def empty() -> "Features":
        return Features(torch.zeros((0, 2), dtype=torch.float32), torch.zeros((0, 128), dtype=torch.float32))


@dataclass(frozen=True)
class SiftSettings:
    """Detector settings shared by both backends.

    Attributes:
        backend: ``"opencv"`` or ``"kornia"``.
        contrast_threshold: OpenCV's ``contrastThreshold`` (on a [0, 1] image); the kornia
            backend keeps responses above ``contrast_threshold / octave_layers / 2``,
            OpenCV's own rejection level.
        octave_layers: scales per octave.
        max_features: upper bound on kornia's keypoints (OpenCV keeps all).
        keypoint_erode: size of the extra square erosion of the contact that keypoints
            must fall inside (px).
        edge_threshold: OpenCV's ``edgeThreshold`` (opencv backend only): extrema whose
            principal curvature ratio exceeds it lie on a line and are dropped.
    """

    backend: str = "opencv"
    contrast_threshold: float = 0.02
    octave_layers: int = 3
    max_features: int = 512
    keypoint_erode: int = 5
    edge_threshold: float = 10.0


def curvature_image(curvature: torch.Tensor, clip: float) -> torch.Tensor:
    """8-bit image of a curvature map: ``trunc((L + clip) / (2 clip) * 255)``.

    Args:
        curvature: ``(H, W)`` or ``(B, H, W)`` 1/px, already clipped to ``[-clip, clip]``.
        clip: the curvature clip (``CurvatureConfig.clip``), > 0.

    Returns:
        uint8 tensor of the same shape (``L = 0`` -> 127).
    """
    if not clip > 0:
        raise FeatureError(f"curvature clip must be > 0, got {clip}")
    scaled = ((curvature.double().clamp(-clip, clip) + clip) / (2.0 * clip) * 255.0).clamp(0.0, 255.0)
    return scaled.to(torch.uint8)  # truncation toward zero, as the reference


def grey_image(bgr: torch.Tensor) -> torch.Tensor:
    """``(H, W, 3)`` uint8 BGR -> ``(H, W)`` uint8 grey (OpenCV's BGR2GRAY weights)."""
    if bgr.ndim != 3 or bgr.shape[-1] != 3 or bgr.dtype != torch.uint8:
        raise FeatureError(f"expected a (H, W, 3) uint8 BGR image, got {tuple(bgr.shape)} {bgr.dtype}")
    return torch.from_numpy(cv2.cvtColor(np.ascontiguousarray(bgr.cpu().numpy()), cv2.COLOR_BGR2GRAY))


def _check_maps(image: torch.Tensor, contact: torch.Tensor) -> None:
    if image.ndim != 2:
        raise FeatureError(f"expected a single (H, W) image, got shape {tuple(image.shape)}")
    if tuple(contact.shape) != tuple(image.shape) or contact.dtype != torch.bool:
        raise FeatureError(f"contact must be a (H, W) bool mask matching the image, got {tuple(contact.shape)} "
                           f"{contact.dtype}")


@lru_cache(maxsize=4)
def _opencv_sift(contrast_threshold: float, octave_layers: int, edge_threshold: float) -> cv2.SIFT:
    return cv2.SIFT_create(nfeatures=0, nOctaveLayers=octave_layers, contrastThreshold=contrast_threshold,
                           edgeThreshold=edge_threshold)


@lru_cache(maxsize=4)
def _kornia_sift(max_features: int, device: str):
    import kornia.feature as KF

    return KF.SIFTFeatureScaleSpace(num_features=max_features, upright=False, rootsift=False,
                                    device=torch.device(device), descriptor_layout="opencv").eval()


def _detect_opencv(crop: np.ndarray, s: SiftSettings) -> tuple[np.ndarray, np.ndarray]:
    kps, desc = _opencv_sift(s.contrast_threshold, s.octave_layers, s.edge_threshold).detectAndCompute(crop, None)
    if desc is None or len(kps) == 0:
        return np.zeros((0, 2), np.float32), np.zeros((0, 128), np.float32)
    return np.array([k.pt for k in kps], dtype=np.float32), desc.astype(np.float32)


def _detect_kornia(crop: torch.Tensor, s: SiftSettings) -> tuple[torch.Tensor, torch.Tensor]:
    from kornia.feature import get_laf_center

    img = crop.float().div(255.0)[None, None]
    with torch.inference_mode():
        lafs, resp, desc = _kornia_sift(s.max_features, str(img.device))(img)
    keep = resp[0] > s.contrast_threshold / s.octave_layers / 2.0
    # kornia's descriptors are unit-norm; OpenCV's have norm 512 (matching thresholds
    # are not used, but a common scale keeps the two backends interchangeable)
    return get_laf_center(lafs)[0][keep].float().cpu(), (desc[0][keep] * 512.0).float().cpu()


def detect(image: torch.Tensor, contact: torch.Tensor, settings: SiftSettings | None = None) -> Features:
    """SIFT inside a contact region.

    Crops ``image`` to the bounding box of ``contact``, runs SIFT there, shifts the
    keypoints back, and keeps those where the contact eroded by
    ``settings.keypoint_erode`` (out-of-image = non-contact) is true at the rounded
    keypoint.

    Args:
        image: ``(H, W)`` uint8.
        contact: ``(H, W)`` bool eroded contact mask.
        settings: detector settings (defaults if ``None``).

    Returns:
        :class:`Features` on the CPU; empty when there is no contact or no keypoint.
    """
    s = settings or SiftSettings()
    if s.backend not in SIFT_BACKENDS:
        raise FeatureError(f"SIFT backend must be one of {SIFT_BACKENDS}, got {s.backend!r}")
    _check_maps(image, contact)
    if image.dtype != torch.uint8:
        raise FeatureError(f"expected a uint8 image, got {image.dtype}")
    box = mask_bounds(contact)
    if box is None:
        return Features.empty()
    r0, r1, c0, c1 = box
    if s.backend == "opencv":
        crop = np.ascontiguousarray(image[r0:r1, c0:c1].cpu().numpy())
        xy, desc = (torch.from_numpy(a) for a in _detect_opencv(crop, s))
    else:
        xy, desc = _detect_kornia(image[r0:r1, c0:c1], s)
    if xy.shape[0] == 0:
        return Features.empty()
    xy = xy + torch.tensor([c0, r0], dtype=torch.float32)
    inner = erode(contact.cpu()[None], s.keypoint_erode, border_is_contact=False)[0]
    h, w = inner.shape
    cols = xy[:, 0].round().long().clamp(0, w - 1)
    rows = xy[:, 1].round().long().clamp(0, h - 1)
    keep = inner[rows, cols]
    return Features(xy[keep].contiguous(), desc[keep].contiguous())


def curvature_features(curvature: torch.Tensor, contact: torch.Tensor, clip: float,
                       settings: SiftSettings | None = None) -> Features:
    """SIFT on the 8-bit curvature image of one keyframe (method.md section 6.2).

    Args:
        curvature: ``(H, W)`` 1/px (zero outside the contact, clipped).
        contact: ``(H, W)`` bool eroded contact mask.
        clip: the curvature clip (``CurvatureConfig.clip``).
        settings: detector settings.

    Returns:
        :class:`Features`.
    """
    if curvature.ndim != 2:
        raise FeatureError(f"expected a single (H, W) curvature map, got shape {tuple(curvature.shape)}")
    if not bool(torch.isfinite(curvature).all()):
        raise FeatureError("curvature map contains NaN or Inf")
    return detect(curvature_image(curvature, clip), contact, settings)


def gaussian_curvature_features(normals: torch.Tensor, contact: torch.Tensor, ksize: int, sigma: float,
                                clip: float, settings: SiftSettings | None = None) -> Features:
    """SIFT on the 8-bit image (:func:`curvature_image`) of the keyframe's Gaussian
    curvature (:func:`~tactile_slam.geometry.curvature.gaussian_curvature`; ``loop.feature_map:
    gaussian``), from its unit normals ``(H, W, 3)`` and eroded contact ``(H, W)``. Only the
    window the contact pixels read is converted to slopes (the full image's values)."""
    if normals.ndim != 3 or normals.shape[-1] != 3:
        raise FeatureError(f"expected a single (H, W, 3) normal map, got shape {tuple(normals.shape)}")
    _check_maps(normals[..., 2], contact)
    box = mask_bounds(contact)
    if box is None:
        return Features.empty()
    rows, cols = window_around((box[0], box[1] - 1, box[2], box[3] - 1), ksize // 2 + 1, tuple(contact.shape))
    n = normals[rows, cols]
    if not bool(torch.isfinite(n).all()):
        raise FeatureError("normal map contains NaN or Inf")
    slopes = -n[..., :2] / n[..., 2:].clamp_min(1e-6)
    k = torch.zeros(contact.shape, dtype=slopes.dtype)
    k[rows, cols] = gaussian_curvature(slopes[None], contact[rows, cols][None], ksize, sigma, clip)[0]
    return detect(curvature_image(k, clip), contact, settings)


def image_features(bgr: torch.Tensor, contact: torch.Tensor, settings: SiftSettings | None = None) -> Features:
    """SIFT on the raw grey GelSight image within the contact (GS-ImageSIFT ablation).

    Args:
        bgr: ``(H, W, 3)`` uint8 BGR image.
        contact: ``(H, W)`` bool eroded contact mask.
        settings: detector settings.
    """
    return detect(grey_image(bgr), contact, settings)
