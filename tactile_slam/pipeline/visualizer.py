"""Visualizers the pipeline calls; :class:`NullVisualizer` does nothing, so the
pipeline never branches on whether to visualise."""

from __future__ import annotations

from pathlib import Path

import cv2

from tactile_slam.geometry.frame import Frame
from tactile_slam.tracking.keyframe import Keyframe
from tactile_slam.tracking.tracker import TrackStep
from tactile_slam.viz import frame_panel


class NullVisualizer:
    def on_frame(self, frame: Frame, step: TrackStep) -> None:
        """Called after every tracked frame."""

    def on_keyframe(self, keyframe: Keyframe) -> None:
        """Called for every emitted keyframe."""

    def close(self) -> None:
        """Called once at the end of the run."""


class KeyframePanels(NullVisualizer):
    """Writes a geometry panel (height, normals, contact, curvature) per keyframe."""

    def __init__(self, folder: Path):
        self.folder = Path(folder)
        self.folder.mkdir(parents=True, exist_ok=True)

    def on_keyframe(self, keyframe: Keyframe) -> None:
        name = f"kf{keyframe.id:05d}_frame{keyframe.video_index:06d}.png"
        cv2.imwrite(str(self.folder / name), frame_panel(keyframe.frame))
