"""``tactile-slam record SOURCE --out FOLDER``: record a scan folder (``gelsight.avi`` +
``config.yaml``) from a live sensor (``camera:GelSight Mini``) or any other input.

Keep the gel untouched for the first frames: they become the background. Stop with
Ctrl-C, ``--seconds`` or ``--frames``. The frames recorded so far are kept also when
the sensor fails (the command then reports the error).

A recorded scan as the source is copied whole: its video from frame 0 (the background
window included, so the copy keeps the video indices), its ``config.yaml`` (unless
``--config`` is given) and its ``background.png``.
"""

from __future__ import annotations

import argparse
import itertools
import math
import shutil
import warnings
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from tactile_slam.cli.arguments import output_folder, positive_int
from tactile_slam.config import load_config
from tactile_slam.io.dispatch import open_source
from tactile_slam.io.frames import FrameSource
from tactile_slam.io.scan import BACKGROUND_NAME, CONFIG_NAME, VIDEO_NAME, Scan
from tactile_slam.io.video import write_video


def register(sub) -> None:
    p = sub.add_parser("record", help="record a scan folder from a live sensor or another input")
    p.add_argument("source", help="camera:INDEX, camera:NAME (e.g. 'camera:GelSight Mini'), a recorded-scan folder "
                                  "(copied whole, its background window included), a video or an image folder")
    p.add_argument("--out", required=True, type=output_folder, help="scan folder to create")
    p.add_argument("--config", default=None, help="YAML config (ours or GelSLAM's) or a preset name")
    p.add_argument("--seconds", type=positive_seconds, default=None, help="stop after this many seconds of frames")
    p.add_argument("--frames", type=positive_int, default=None,
                   help="stop after this many frames (the background window included)")
    p.add_argument("--resize", action="store_true", help="resize input frames to the working size")
    p.set_defaults(func=run)


def positive_seconds(value: str) -> float:
    """A finite duration > 0 (``--seconds``), checked while parsing, before anything is created."""
    try:
        x = float(value)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number of seconds, got {value!r}") from None
    if not math.isfinite(x) or x <= 0:
        raise argparse.ArgumentTypeError(f"must be a finite number of seconds > 0, got {value}")
    return x


def frames_to_record(source: FrameSource) -> FrameSource:
    """What ``record`` copies from ``source``: a :class:`Scan`'s whole video (its
    background window included; iterating the scan starts after it), else the source."""
    return source.video if isinstance(source, Scan) else source


def recorded_frames(source: FrameSource, max_frames: int | None, max_seconds: float | None) -> Iterator[np.ndarray]:
    """BGR frames of ``source`` until a limit is reached, the source ends, or Ctrl-C."""
    start = None
    try:
        for frame in itertools.islice(source, max_frames):
            start = frame.timestamp if start is None else start
            if max_seconds is not None and frame.timestamp - start >= max_seconds:
                return
            yield frame.bgr
    except KeyboardInterrupt:
        return


def run(args) -> int:
    out = Path(args.out)
    if (out / VIDEO_NAME).exists():
        raise ValueError(f"{out / VIDEO_NAME} exists; choose a new folder")
    # without --config a scan keeps its own config.yaml
    config = load_config(args.config) if args.config else None
    with open_source(args.source, config, resize=args.resize) as source:
        config = config or getattr(source, "config", None) or load_config(None)
        n_bg = config.sensor.background_frames
        out.mkdir(parents=True, exist_ok=True)
        config.save(out / CONFIG_NAME)
        if isinstance(source, Scan) and (source.folder / BACKGROUND_NAME).is_file():
            shutil.copyfile(source.folder / BACKGROUND_NAME, out / BACKGROUND_NAME)
        print(f"record: {source} -> {out}; keep the gel untouched for the first {n_bg} frames, Ctrl-C stops")
        frames = recorded_frames(frames_to_record(source), args.frames, args.seconds)
        n = write_video(out / VIDEO_NAME, frames, source.fps)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            Scan(out, config=config).close()
        except ValueError as exc:
            print(f"record: warning: {exc}")
    for w in caught:
        print(f"record: warning: {w.message}")
    print(f"record: {n} frames ({n / source.fps:.1f} s) in {out}")
    return 0
