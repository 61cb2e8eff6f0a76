"""Pictures: frame geometry (height, normals, contact, curvature) as BGR uint8 images, and
trajectory reports."""

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


def trajectory_report(path, frames: np.ndarray, est: np.ndarray, gt: np.ndarray, fps: float, title: str) -> None:
    """PNG: estimated vs ground-truth translation and rotation over time, and the error.

    Args:
        frames: ``(N,)`` video indices.
        est, gt: ``(N, 6)`` per-axis pose vectors (x, y, z in mm; rx, ry, rz in degrees),
            NaN where there is no estimate.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t = np.asarray(frames) / fps
    names = ["x", "y", "z", "rx", "ry", "rz"]
    fig, axes = plt.subplots(3, 1, figsize=(10, 8), sharex=True)
    for i, name in enumerate(names):
        ax = axes[0] if i < 3 else axes[1]
        line = ax.plot(t, gt[:, i], lw=2.0, alpha=0.35)[0]
        ax.plot(t, est[:, i], lw=0.9, color=line.get_color(), label=name)
        axes[2].plot(t, np.abs(est[:, i] - gt[:, i]), lw=0.8, label=f"{name} ({'mm' if i < 3 else 'deg'})")
    axes[0].set_ylabel("translation (mm)")
    axes[1].set_ylabel("rotation (deg)")
    axes[2].set_ylabel("|error|")
    axes[2].set_xlabel("time (s)")
    axes[0].set_title(f"{title}\nthin: estimate, thick: ground truth")
    for ax in axes:
        ax.legend(loc="upper left", fontsize=8, ncol=6)
        ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def pose_graph_figure(path, positions_mm: np.ndarray, coverage: np.ndarray, odometry: np.ndarray,
                      loops: np.ndarray, title: str) -> None:
    """PNG of a pose graph seen from above (like GelSLAM's Fig. 13).

    Args:
        positions_mm: ``(K, 3)`` keyframe positions in the start frame, mm.
        coverage: ``(K,)`` bool, active coverage keyframes.
        odometry, loops: ``(E, 2)`` row indices into ``positions_mm`` of the edges.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 6))
    p = positions_mm
    for (i, j) in odometry:
        ax.plot(p[[i, j], 0], p[[i, j], 1], color="0.6", lw=0.8, zorder=1)
    for n, (i, j) in enumerate(loops):
        ax.plot(p[[i, j], 0], p[[i, j], 1], color="tab:red", lw=0.6, alpha=0.7, zorder=2,
                label="loop" if n == 0 else None)
    ax.scatter(p[~coverage, 0], p[~coverage, 1], s=8, color="tab:blue", label="keyframe", zorder=3)
    ax.scatter(p[coverage, 0], p[coverage, 1], s=22, color="tab:orange", label="coverage keyframe", zorder=4)
    ax.set_xlabel("x (mm)")
    ax.set_ylabel("y (mm)")
    ax.set_aspect("equal")
    ax.set_title(title)
    ax.legend(loc="best", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
