"""Pictures of frame geometry (height, normals, contact, curvature) as BGR uint8 images."""

from __future__ import annotations

import cv2
import numpy as np

from tactile_slam.geometry.frame import Frame


def _colormap(x: np.ndarray, lo: float, hi: float, cmap: int) -> np.ndarray:
    u = np.clip((x - lo) / max(hi - lo, 1e-12), 0, 1)
    return cv2.applyColorMap((u * 255).astype(np.uint8), cmap)


def _label(img: np.ndarray, text: str) -> np.ndarray:
    img = img.copy()
    cv2.putText(img, text, (6, 18), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (255, 255, 255), 1, cv2.LINE_AA)
    return img


def frame_panel(frame: Frame, i: int = 0, bgr: np.ndarray | None = None) -> np.ndarray:
    """A 2x2 (or 2x3 with the input image) mosaic: height, normals, contact, curvature.

    Args:
        frame: a frame batch; element ``i`` is drawn.
        bgr: optional ``(H, W, 3)`` uint8 input image shown first.

    Returns:
        ``(2H, 2W or 3W, 3)`` uint8 BGR.
    """
    h = frame.height[i].cpu().numpy()
    depth_mm = -h.min() * frame.mm_per_px
    height = _label(_colormap(h, h.min(), max(h.max(), 0.0), cv2.COLORMAP_VIRIDIS), f"height (depth {depth_mm:.2f} mm)")
    n = frame.normals[i].cpu().numpy()
    normals = _label(((n[..., ::-1] * 0.5 + 0.5) * 255).astype(np.uint8), "normals")
    c = frame.contact[i].cpu().numpy()
    contact = _label(np.repeat((c[..., None] * 255).astype(np.uint8), 3, axis=2), f"contact ({int(c.sum())} px)")
    lap = frame.curvature[i].cpu().numpy()
    m = max(float(np.abs(lap).max()), 1e-6)
    curv = _label(_colormap(lap, -m, m, cv2.COLORMAP_JET), f"curvature (|L| <= {m:.3f}/px)")
    top = [height, normals]
    bottom = [contact, curv]
    if bgr is not None:
        top = [_label(bgr, "input")] + top
        bottom = [np.zeros_like(bgr)] + bottom
    return np.vstack([np.hstack(top), np.hstack(bottom)])
