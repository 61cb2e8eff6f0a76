"""Keyframe poses from odometry alone (no loop closure): each session is its own group."""

from __future__ import annotations

import torch

from tactile_slam.tracking.keyframe import Keyframe


class OdometryMap:
    """Chains each session's keyframe measurements from its head.

    ``start_T_kf[id]`` is the keyframe's pose in its group's start frame (the head's
    sensor frame), metres; ``group[id]`` is the session id.
    """

    def __init__(self) -> None:
        self.start_T_kf: dict[int, torch.Tensor] = {}
        self.group: dict[int, int] = {}
        self._last_in_session: dict[int, int] = {}

    def add(self, kf: Keyframe) -> None:
        if kf.new_session or kf.session not in self._last_in_session:
            pose = torch.eye(4, dtype=torch.float64)
        else:
            pose = self.start_T_kf[self._last_in_session[kf.session]] @ kf.prev_T_kf
        self.start_T_kf[kf.id] = pose
        self.group[kf.id] = kf.session
        self._last_in_session[kf.session] = kf.id

    def finish(self) -> None:
        """Nothing to optimise."""
