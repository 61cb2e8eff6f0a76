"""A one-session scene with a loop, shared by the back-end tests."""

from __future__ import annotations

import torch

from tactile_slam.config import Config
from tactile_slam.geometry.frame import FrameBuilder
from tactile_slam.posegraph import se3
from tactile_slam.tracking.keyframe import Keyframe
from tests.registration.surfaces import frames, rigid, textured


def revisit_keyframes(slope_noise: float = 0.0, tilt_deg: float = 1.5) -> tuple[list[Keyframe], torch.Tensor]:
    """Keyframe 0, keyframe 1 moved away, keyframe 2 back near 0 (a loop to 0) and tilted
    from it by ``tilt_deg`` about x, with true odometry; slopes carry i.i.d. noise of
    ``slope_noise`` (seeded).

    Returns:
        ``(keyframes, kf0_T)``: ``kf0_T`` ``(3, 4, 4)`` float64 each keyframe's true pose in
        keyframe 0's frame (metres).
    """
    views = [torch.eye(4, dtype=torch.float64), rigid(rz_deg=8.0, tx_mm=1.5),
             rigid(rx_deg=tilt_deg, rz_deg=3.0, ty_mm=0.3)]
    f = frames(textured(5), views)
    if slope_noise:
        noise = slope_noise * torch.randn(f.gradients.shape, generator=torch.Generator().manual_seed(1))
        f = FrameBuilder(Config()).from_gradients((f.gradients + noise).float(), f.contact)
    kf0_T = [se3.inverse(v) for v in views]  # keyframe k's pose in keyframe 0's frame
    kfs = [Keyframe(k, 0, f[k], k == 0, torch.eye(4, dtype=torch.float64) if k == 0 else
                    se3.inverse(kf0_T[k - 1]) @ kf0_T[k]) for k in range(3)]
    return kfs, torch.stack(kf0_T)
