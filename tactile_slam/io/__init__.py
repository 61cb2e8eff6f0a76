"""Sensor input: recorded scans, videos, image folders, gradient-map sequences, live cameras.

Every source yields :class:`RawFrame` records in video order; recordings also offer
``len()`` and random access and can back a :class:`FrameDataset`. See ``docs/io.md``.
"""

from tactile_slam.geometry.frame import InputError
from tactile_slam.io.camera import CameraSource, crop_box, crop_raw, find_camera, list_video_devices
from tactile_slam.io.dataset import FrameBatch, FrameDataset, collate, iter_batches
from tactile_slam.io.dispatch import open_source
from tactile_slam.io.frames import FrameSource, RawFrame, SequenceSource
from tactile_slam.io.gradients import GradientSequence
from tactile_slam.io.images import ImageFolder
from tactile_slam.io.scan import BackgroundCheck, BackgroundWarning, Scan, check_background, load_background
from tactile_slam.io.video import VideoSource, write_video

__all__ = [
    "BackgroundCheck",
    "BackgroundWarning",
    "CameraSource",
    "FrameBatch",
    "FrameDataset",
    "FrameSource",
    "GradientSequence",
    "ImageFolder",
    "InputError",
    "RawFrame",
    "Scan",
    "SequenceSource",
    "VideoSource",
    "check_background",
    "collate",
    "crop_box",
    "crop_raw",
    "find_camera",
    "iter_batches",
    "list_video_devices",
    "load_background",
    "open_source",
    "write_video",
]
