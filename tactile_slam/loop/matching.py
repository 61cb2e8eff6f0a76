"""Descriptor matching, the 2-D similarity model and its SE(3) lift (method.md section 6.3).

``match`` pairs reference and target keypoints by brute-force L2 nearest neighbours
with a cross-check (the reference is the query side, no ratio test), then fits a 4-DoF
similarity ``p_tar = A p_ref + m`` (rotation, uniform scale, translation) by RANSAC
with OpenCV's partial-affine estimator and LM refinement on the inliers. The
estimator only runs with at least ``min_inliers`` matches (degenerate input can make
it fail), and the pair is a loop candidate only when it keeps ``min_inliers`` inliers
and the alignment is unambiguous: a second RANSAC on the outliers must not find a
distinct alignment with comparable support (a periodic texture, e.g. a knurl, matches
itself shifted by whole periods; such pairs cannot be told apart from the data).

``similarity_to_se3`` lifts the 2-D model to an initial ``tar_T_ref``: a rotation about
the sensor z axis by the similarity's rotation (scale dropped, no tilt) and the
in-plane translation of the image centre ``c = ((W - 1) / 2, (H - 1) / 2)``, the
metric origin of method.md 1.2. (The public code uses ``(W / 2, H / 2)``, which biases
the translation by half a pixel times the rotation.)
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import cv2
import numpy as np
import torch

from tactile_slam.loop.features import Features


class MatchingError(ValueError):
    """Unusable matching input (wrong shapes, NaN, bad model)."""


@dataclass(frozen=True)
class RansacSettings:
    """RANSAC for the 2-D similarity (OpenCV ``estimateAffinePartial2D``).

    Attributes:
        min_inliers: least matches to try and least inliers to accept.
        iterations: RANSAC iterations.
        threshold_px: reprojection threshold (px).
        confidence: RANSAC confidence.
        refine_iters: LM refinement iterations on the inliers.
        ambiguity_ratio: reject the pair when a second, distinct similarity fitted to
            the first one's outliers keeps at least this fraction of its inliers (and at
            least ``min_inliers // 2``): the texture supports two alignments, as a
            periodic one does. ``None`` disables the test.
    """

    min_inliers: int = 8
    iterations: int = 100
    threshold_px: float = 3.0
    confidence: float = 0.99
    refine_iters: int = 10
    ambiguity_ratio: float | None = 0.5


@dataclass
class Similarity:
    """A 2-D similarity between two keyframes' pixels.

    Attributes:
        M: ``(2, 3)`` float64 ``[A | m]`` mapping reference pixels ``(x, y)`` to target
            pixels: ``p_tar = A p_ref + m``.
        inliers: RANSAC inlier count.
        matches: cross-checked matches it was fitted to.
        second: inliers of the best distinct alternative fitted to the outliers (0 if
            none was tried).
    """

    M: np.ndarray
    inliers: int
    matches: int
    second: int = 0


def _as_np(x: torch.Tensor | np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(x.detach().cpu().numpy() if isinstance(x, torch.Tensor) else x, dtype=np.float32)


def match_descriptors(ref: torch.Tensor | np.ndarray, tar: torch.Tensor | np.ndarray) -> np.ndarray:
    """Cross-checked brute-force L2 matches.

    Args:
        ref: ``(N, D)`` reference descriptors (the query side).
        tar: ``(M, D)`` target descriptors.

    Returns:
        ``(K, 2)`` int64 ``(ref index, tar index)`` pairs, each the other's nearest
        neighbour; ``K = 0`` when either side is empty.
    """
    ref, tar = _as_np(ref), _as_np(tar)
    if ref.ndim != 2 or tar.ndim != 2 or ref.shape[1] != tar.shape[1]:
        raise MatchingError(f"descriptors must be (N, D) and (M, D), got {ref.shape} and {tar.shape}")
    if len(ref) == 0 or len(tar) == 0:
        return np.zeros((0, 2), np.int64)
    if not (np.isfinite(ref).all() and np.isfinite(tar).all()):
        raise MatchingError("descriptors contain NaN or Inf")
    found = cv2.BFMatcher(cv2.NORM_L2, crossCheck=True).match(ref, tar)
    return np.array([(m.queryIdx, m.trainIdx) for m in found], dtype=np.int64).reshape(-1, 2)


def estimate_similarity(ref_xy: np.ndarray, tar_xy: np.ndarray, settings: RansacSettings | None = None
                        ) -> Similarity | None:
    """RANSAC 4-DoF similarity ``tar = A ref + m`` between matched pixel positions.

    Args:
        ref_xy: ``(K, 2)`` reference keypoints ``(x, y)`` px.
        tar_xy: ``(K, 2)`` matched target keypoints.
        settings: RANSAC settings.

    Returns:
        the :class:`Similarity`, or ``None`` when there are fewer than
        ``min_inliers`` matches or inliers, or the estimator fails.
    """
    s = settings or RansacSettings()
    ref_xy, tar_xy = _as_np(ref_xy), _as_np(tar_xy)
    if ref_xy.shape != tar_xy.shape or ref_xy.ndim != 2 or ref_xy.shape[1] != 2:
        raise MatchingError(f"matched points must be two (K, 2) arrays, got {ref_xy.shape} and {tar_xy.shape}")
    if len(ref_xy) < max(s.min_inliers, 2):
        return None
    M, mask = _ransac(ref_xy, tar_xy, s)
    if M is None:
        return None
    inliers = int(mask.sum())
    if inliers < s.min_inliers:
        return None
    second = 0
    floor = max(s.min_inliers // 2, 2)
    if s.ambiguity_ratio is not None and len(ref_xy) - inliers >= floor:
        out = ~mask
        _, mask2 = _ransac(ref_xy[out], tar_xy[out], s)
        second = 0 if mask2 is None else int(mask2.sum())
        if second >= max(floor, s.ambiguity_ratio * inliers):
            return None
    return Similarity(M.astype(np.float64), inliers, len(ref_xy), second)


def _ransac(ref_xy: np.ndarray, tar_xy: np.ndarray, s: RansacSettings) -> tuple[np.ndarray | None, np.ndarray | None]:
    """OpenCV's RANSAC similarity; ``(M (2, 3), inlier mask (K,) bool)`` or ``(None, None)``."""
    M, mask = cv2.estimateAffinePartial2D(
        ref_xy, tar_xy, method=cv2.RANSAC, ransacReprojThreshold=s.threshold_px, maxIters=s.iterations,
        confidence=s.confidence, refineIters=s.refine_iters,
    )
    if M is None or mask is None or not np.isfinite(M).all():
        return None, None
    return M, mask.ravel().astype(bool)


def match(ref: Features, tar: Features, settings: RansacSettings | None = None) -> Similarity | None:
    """Match two keyframes' features and fit the 2-D similarity ref -> tar pixels.

    Returns:
        the :class:`Similarity`, or ``None`` if the pair is not a loop candidate.
    """
    s = settings or RansacSettings()
    if len(ref) < s.min_inliers or len(tar) < s.min_inliers:
        return None
    pairs = match_descriptors(ref.descriptors, tar.descriptors)
    if len(pairs) < s.min_inliers:
        return None
    return estimate_similarity(ref.keypoints.numpy()[pairs[:, 0]], tar.keypoints.numpy()[pairs[:, 1]], s)


def self_similarity(feats: Features, settings: RansacSettings | None = None) -> Similarity | None:
    """A 2-D similarity that maps a keyframe's texture onto *another part of itself*, or None.

    Each keypoint is paired with its nearest descriptor among the keypoints farther than
    three RANSAC thresholds from it (cross-checked), and the similarity is fitted to those
    pairs with the loop's own RANSAC settings (no ambiguity test). A periodic texture
    (a knurl's lattice, a grating) matches itself shifted by whole periods and yields one;
    an aperiodic one does not. Such a keyframe matches the same texture elsewhere on the
    object as well as the right place, so its loops are no independent evidence.

    Returns:
        the :class:`Similarity` between keypoint positions (``inliers`` counts distinct
        keypoint pairs), or ``None``.
    """
    s = replace(settings or RansacSettings(), ambiguity_ratio=None)
    xy, d = feats.keypoints, feats.descriptors
    if xy.ndim != 2 or xy.shape[1] != 2 or d.ndim != 2 or len(d) != len(xy):
        raise MatchingError(f"features must be (N, 2) keypoints and (N, D) descriptors, got "
                            f"{tuple(xy.shape)} and {tuple(d.shape)}")
    if not (torch.isfinite(xy).all() and torch.isfinite(d).all()):
        raise MatchingError("keypoints or descriptors contain NaN or Inf")
    if len(feats) < s.min_inliers:
        return None
    xy = xy.double()
    dist = torch.cdist(d.double(), d.double())
    dist[torch.cdist(xy, xy) <= 3.0 * s.threshold_px] = torch.inf  # itself and its neighbourhood
    nearest, nn = dist.min(1)
    idx = torch.arange(len(feats))
    mutual = idx[(nn[nn] == idx) & torch.isfinite(nearest)]
    if len(mutual) < s.min_inliers:
        return None
    src, dst = mutual.numpy(), nn[mutual].numpy()
    pts = feats.keypoints.numpy()
    M, mask = _ransac(pts[src], pts[dst], s)
    if M is None:
        return None
    # a mutual pair enters in both directions, and a half turn about its midpoint maps each
    # onto the other: count keypoint pairs, not directions, so every kind of self-map needs
    # min_inliers distinct pairs
    pairs = {(min(a, b), max(a, b)) for a, b in zip(src[mask], dst[mask])}
    if len(pairs) < s.min_inliers:
        return None
    return Similarity(M.astype(np.float64), len(pairs), len(src))


def similarity_to_se3(M: np.ndarray | torch.Tensor, shape: tuple[int, int], m_per_px: float) -> torch.Tensor:
    """Lift a pixel similarity ``p_tar = A p_ref + m`` to an initial ``tar_T_ref``.

    With ``sigma = sqrt(M00^2 + M01^2)`` and ``R2 = A / sigma`` (scale dropped), the
    result rotates by ``R2`` about z and translates by ``((A c + m - c) s, 0)``, where
    ``c = ((W - 1) / 2, (H - 1) / 2)`` is the image centre and ``s`` the pixel size:
    a target pattern shifted by ``+dx`` px gives ``+dx s`` in x (method.md 1.4).

    Args:
        M: ``(2, 3)`` similarity.
        shape: ``(H, W)`` image size.
        m_per_px: metres per pixel.

    Returns:
        ``(4, 4)`` float64 ``tar_T_ref`` in metres (maps reference-sensor coordinates
        into target-sensor coordinates).
    """
    M = torch.as_tensor(np.asarray(M), dtype=torch.float64)
    if M.shape != (2, 3) or not bool(torch.isfinite(M).all()):
        raise MatchingError(f"similarity must be a finite (2, 3) matrix, got {tuple(M.shape)}")
    sigma = float(torch.hypot(M[0, 0], M[0, 1]))
    if not sigma > 0:
        raise MatchingError("similarity has zero scale")
    h, w = shape
    c = torch.tensor([(w - 1) / 2.0, (h - 1) / 2.0], dtype=torch.float64)
    A, m = M[:, :2], M[:, 2]
    T = torch.eye(4, dtype=torch.float64)
    T[:2, :2] = A / sigma
    T[:2, 3] = (A @ c + m - c) * m_per_px
    return T
