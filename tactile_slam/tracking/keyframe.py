"""Keyframe record shared by tracking, loop closure, the pose graph and reconstruction."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import torch

from tactile_slam.geometry.frame import CroppedFrame, Frame, crop_to_contact


@dataclass
class Keyframe:
    """One keyframe (method.md section 5.2).

    Attributes:
        id: keyframe id, sequential over the whole run.
        session: tracking-session id (a contiguous contact period tracked without an
            unrecoverable failure); the session's first keyframe is its head.
        maps: the keyframe's geometry as stored: a :class:`Frame` with ``B = 1``, or a
            :class:`CroppedFrame` (the maps around the contact only, a fraction of the
            memory on a long scan: what the pipelines keep once the back end has taken
            the keyframe in, :meth:`compact`). Read it through :attr:`frame`.
        new_session: True for a session head.
        prev_T_kf: ``(4, 4)`` float64, metres: this keyframe's pose in the previous
            keyframe of the same session (the odometry measurement); identity for a
            session head.
        image: optional ``(H, W, 3)`` uint8 BGR image of the keyframe (GS-ImageSIFT).
        prepared: the tracker's NormalFlow preparation of these maps as a reference (a
            :class:`~tactile_slam.registration.normalflow.PreparedReference`), while the
            keyframe is new: loop verification, which uses the new keyframe as its
            reference, reuses it instead of preparing it again. :meth:`compact` drops it.
    """

    id: int
    session: int
    maps: Frame | CroppedFrame
    new_session: bool
    prev_T_kf: torch.Tensor
    image: torch.Tensor | None = None
    prepared: Any = field(default=None, repr=False, compare=False)

    @property
    def frame(self) -> Frame:
        """The full-size geometry, ``B = 1`` (a cropped keyframe builds new tensors on each
        access: bind it once where several maps are read)."""
        return self.maps.expand() if isinstance(self.maps, CroppedFrame) else self.maps

    def compact(self) -> None:
        """Keep only the maps around the contact from now on (:func:`crop_to_contact`), and
        drop the tracker's preparation: what a pipeline does once the back end has taken
        the keyframe in."""
        self.prepared = None
        if isinstance(self.maps, Frame):
            self.maps = crop_to_contact(self.maps)

    @property
    def video_index(self) -> int:
        return int(self._stored.index[0])

    @property
    def depth_known(self) -> bool:
        """Whether undeformed gel was in view, so its heights (and the z of every
        registration against it) have a known zero (:attr:`Frame.depth_known`)."""
        return bool(self._stored.depth_known[0])

    @property
    def decoded(self) -> bool:
        """Whether its gradients were decoded from an image (:attr:`Frame.decoded`)."""
        return self.maps.decoded

    @property
    def has_contact(self) -> bool:
        return bool(self._stored.contact.any())

    @property
    def _stored(self) -> Frame:
        """The stored maps: the full frame, or a crop's box."""
        return self.maps.box if isinstance(self.maps, CroppedFrame) else self.maps
