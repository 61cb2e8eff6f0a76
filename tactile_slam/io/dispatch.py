"""``open_source``: one entry point from a path or device spec to the right source."""

from __future__ import annotations

from pathlib import Path

from tactile_slam.config import Config
from tactile_slam.geometry.frame import InputError
from tactile_slam.io.camera import CameraSource
from tactile_slam.io.frames import FrameSource
from tactile_slam.io.gradients import CONTACT_NPY, EPISODE_NPZ, GRADIENTS_NPY, GradientSequence
from tactile_slam.io.images import ImageFolder, list_images
from tactile_slam.io.scan import VIDEO_NAME, Scan
from tactile_slam.io.video import VIDEO_SUFFIXES, VideoSource

CAMERA_PREFIX = "camera:"


def open_source(spec: str | Path, config: Config | None = None, resize: bool = False) -> FrameSource:
    """Open whatever ``spec`` names.

    ============================================  =================================
    ``spec``                                      source
    ============================================  =================================
    ``camera:0`` / ``camera:GelSight Mini``       :class:`CameraSource` (index / V4L2 name)
    folder with ``gelsight.avi``                  :class:`Scan`
    folder with ``gradient_maps.npy``             :class:`GradientSequence`
    folder with images                            :class:`ImageFolder`
    ``.npz`` or ``.npy`` file                     :class:`GradientSequence`
    video file (``.avi``, ``.mkv``, ``.mp4``...)  :class:`VideoSource`
    ============================================  =================================

    Args:
        spec: path or camera spec.
        config: sensor settings (working size, fps, raw size). ``None`` lets a scan use
            its own ``config.yaml``, and everything else the GelSight Mini preset.
        resize: resize image frames of another size to the working size instead of
            raising.

    Raises:
        InputError: the path does not exist or holds nothing readable.
    """
    if isinstance(spec, str) and spec.startswith(CAMERA_PREFIX):
        sensor = (config or Config()).sensor
        device = spec[len(CAMERA_PREFIX):].strip()
        if not device:
            raise InputError(f"camera spec {spec!r} names no device (use camera:0 or camera:GelSight Mini)")
        return CameraSource(
            int(device) if device.isdigit() else device,
            shape=sensor.shape,
            fps=sensor.fps,
            raw_shape=(sensor.raw_height, sensor.raw_width),
        )
    path = Path(spec)
    if path.is_dir() and (path / VIDEO_NAME).is_file():
        return Scan(path, config=config, resize=resize)
    sensor = (config or Config()).sensor
    if path.is_dir():
        if (path / GRADIENTS_NPY).is_file() or (path / CONTACT_NPY).is_file():
            return GradientSequence(path, fps=sensor.fps, shape=sensor.shape)
        if list_images(path):
            return ImageFolder(path, fps=sensor.fps, shape=sensor.shape, resize=resize)
        if (path / EPISODE_NPZ).is_file():  # a gradient-level simulated episode (no video)
            return GradientSequence(path / EPISODE_NPZ, fps=sensor.fps, shape=sensor.shape)
        raise InputError(
            f"{path} holds no {VIDEO_NAME}, no {GRADIENTS_NPY}, no {EPISODE_NPZ} and no images: nothing to read"
        )
    if not path.exists():
        raise InputError(f"input not found: {path}")
    suffix = path.suffix.lower()
    if suffix in (".npz", ".npy"):
        return GradientSequence(path, fps=sensor.fps, shape=sensor.shape)
    if suffix in VIDEO_SUFFIXES:
        return VideoSource(path, shape=sensor.shape, resize=resize)
    raise InputError(f"unsupported input file type {suffix or '(none)'!r}: {path}")
