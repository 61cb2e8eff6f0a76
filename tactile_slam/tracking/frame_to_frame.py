"""Frame-to-frame NormalFlow without keyframes: the "NF" baseline of method.md 9.5.

Each frame is registered against the previous one and the estimates are composed; a
new session starts only when contact starts, and a running one goes on through frames
above ``keep_contact_mm2`` as in :class:`Tracker`. Same ``step`` interface as
:class:`tactile_slam.tracking.tracker.Tracker`: the session head plays the keyframe,
so ``kf_T_frame`` is the frame's pose in the session's first frame.
"""

from __future__ import annotations

import torch

from tactile_slam.geometry.frame import Frame, own_maps
from tactile_slam.tracking.keyframe import Keyframe
from tactile_slam.tracking.tracker import Registrar, TrackStep, check_keep_contact, holds_contact


class FrameToFrameTracker:
    def __init__(self, registrar: Registrar, keep_contact_mm2: float | None = None):
        check_keep_contact(keep_contact_mm2)
        self.registrar = registrar
        self.keep_contact_mm2 = keep_contact_mm2
        self.head: Keyframe | None = None
        self.prev_prepared = None
        self.head_T_prev = torch.eye(4, dtype=torch.float64)
        self.next_id = 0

    def step(self, frame: Frame) -> TrackStep:
        """Track one frame (``B = 1``)."""
        index = int(frame.index[0])
        if not holds_contact(frame, self.prev_prepared is not None, self.keep_contact_mm2):
            self.prev_prepared = None
            return TrackStep(index=index, in_contact=False)
        if self.prev_prepared is None:
            eye = torch.eye(4, dtype=torch.float64)
            self.head = Keyframe(self.next_id, self.next_id, own_maps(frame), True, eye)
            self.next_id += 1
            self.head_T_prev, self.prev_prepared = eye, self.registrar.prepare(frame)
            return TrackStep(index, True, eye, self.head.id, self.head.session, keyframes=[self.head], is_keyframe=True)
        res = self.registrar.register(self.prev_prepared, frame, torch.eye(4, dtype=torch.float64)[None])[0]
        prev_T_frame = torch.linalg.inv(res.tar_T_ref[0].to(torch.float64).cpu())
        self.head_T_prev = self.head_T_prev @ prev_T_frame
        self.prev_prepared = self.registrar.prepare(frame)
        return TrackStep(index, True, self.head_T_prev.clone(), self.head.id, self.head.session,
                         float(res.ccs[0]), float(res.scr[0]), conditioning=float(res.conditioning[0]))

    def finish(self) -> list[Keyframe]:
        self.prev_prepared = None
        return []
