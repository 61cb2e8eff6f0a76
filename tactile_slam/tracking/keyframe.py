"""Keyframe record shared by tracking, loop closure, the pose graph and reconstruction."""

from __future__ import annotations

from dataclasses import dataclass

import torch

from tactile_slam.geometry.frame import Frame


@dataclass
class Keyframe:
    """One keyframe (method.md section 5.2).

    Attributes:
        id: keyframe id, sequential over the whole run.
        session: tracking-session id (a contiguous contact period tracked without an
            unrecoverable failure); the session's first keyframe is its head.
        frame: the keyframe's geometry, a :class:`Frame` with ``B = 1`` and maps of its
            own; the trackers store it without gradients (``None``), which nothing reads.
        new_session: True for a session head.
        prev_T_kf: ``(4, 4)`` float64, metres: this keyframe's pose in the previous
            keyframe of the same session (the odometry measurement); identity for a
            session head.
        image: optional ``(H, W, 3)`` uint8 BGR image of the keyframe (GS-ImageSIFT).
    """

    id: int
    session: int
    frame: Frame
    new_session: bool
    prev_T_kf: torch.Tensor
    image: torch.Tensor | None = None

    @property
    def video_index(self) -> int:
        return int(self.frame.index[0])
