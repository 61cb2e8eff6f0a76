"""Sensor input: FFV1 decode and encode per frame, batched loading, live-frame crop and resize.

All timings are per frame, in ms, on synthetic sensor-like frames (a smooth colour field
plus Gaussian noise of 1.5 levels, which sets FFV1's compression work) at the working
size. A GelSight Mini delivers a frame every 40 ms.
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

import numpy as np
import torch
from torch.utils.data import DataLoader

from tactile_slam.bench.common import time_fn, timing_stats, write_json
from tactile_slam.cli.arguments import positive_int
from tactile_slam.config import Config
from tactile_slam.io.camera import crop_raw
from tactile_slam.io.dataset import FrameDataset, collate
from tactile_slam.io.video import VideoSource, write_video


def add_arguments(parser) -> None:
    parser.add_argument("--frames", type=positive_int, default=300, help="frames in the test video (>= 200)")
    parser.add_argument("--batch-size", type=positive_int, default=16)


def sensor_like_frames(n: int, shape: tuple[int, int], seed: int = 0) -> np.ndarray:
    """``(n, H, W, 3)`` uint8: smooth colour field + N(0, 1.5) noise."""
    h, w = shape
    yy, xx = np.mgrid[:h, :w].astype(np.float32)
    base = np.stack([100 + 50 * np.sin(xx / 30), 120 + 40 * np.cos(yy / 25), 90 + 0.2 * xx], axis=-1)
    rng = np.random.default_rng(seed)
    noise = rng.normal(0.0, 1.5, (n, h, w, 3)).astype(np.float32)
    return np.clip(np.round(base + noise), 0, 255).astype(np.uint8)


def _per_frame(samples_s: list[float], frames_per_sample: int) -> dict:
    return timing_stats(np.asarray(samples_s) / frames_per_sample)


def run(args) -> Path:
    if args.frames < 200:
        raise ValueError(f"--frames must be >= 200, got {args.frames}")
    sensor = Config().sensor
    frames = sensor_like_frames(args.frames, sensor.shape)
    results = {"frames": args.frames, "shape": list(sensor.shape), "batch_size": args.batch_size}
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "gelsight.avi"
        t0 = time.perf_counter()
        write_video(path, frames, fps=sensor.fps)
        results["write_ffv1_per_frame_ms"] = (time.perf_counter() - t0) * 1000 / args.frames
        results["ffv1_bytes_per_frame"] = path.stat().st_size / args.frames

        source = VideoSource(path, shape=sensor.shape)
        stream = iter(source)
        results["stream_decode"] = timing_stats(time_fn(lambda: next(stream), repeats=args.frames - 5, warmup=5))

        order = np.random.default_rng(1).permutation(len(source))
        pos = iter(np.tile(order, 2))
        results["random_access"] = timing_stats(time_fn(lambda: source[int(next(pos))], repeats=200, warmup=5))

        def load_all() -> None:
            loader = DataLoader(FrameDataset(source), batch_size=args.batch_size, collate_fn=collate)
            for _ in loader:
                pass

        results["dataloader_all_frames"] = _per_frame(time_fn(load_all, repeats=3, warmup=1), len(source))
        source.close()

    raw = np.random.default_rng(2).integers(0, 256, (sensor.raw_height, sensor.raw_width, 3), dtype=np.uint8)
    results["camera_crop_resize"] = timing_stats(time_fn(lambda: crop_raw(raw, sensor.shape), repeats=200))
    results["torch_threads"] = torch.get_num_threads()
    return write_json(args.out, "io", results)
