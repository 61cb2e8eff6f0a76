"""Real-time replay: frames processed vs dropped, latency, skipped loop detections, online vs offline accuracy.

A simulated episode (gradient level) is replayed at the sensor's frame rate through
the online pipeline, looped to each requested length (the issue's 7-minute case is
10,500 frames at 25 Hz; the loop restarts with a lift-off, so later passes relocalise
against earlier ones). Per replay: frames processed and dropped, per-frame latency
(median, p95), keyframes skipped for loop detection, loops, back-end errors, and the
per-axis MAE of the largest group against ground truth, next to the offline
pipeline's on the same frames (up to ``--offline-max-frames``).
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from tactile_slam.bench.common import write_json
from tactile_slam.cli.arguments import positive_int
from tactile_slam.config import Config
from tactile_slam.eval.tracking_metrics import per_axis_mae
from tactile_slam.io.gradients import EPISODE_NPZ, GradientSequence
from tactile_slam.io.replay import LoopedSource
from tactile_slam.pipeline.offline import OfflinePipeline, RunOptions, RunResult
from tactile_slam.pipeline.online import OnlineOptions, OnlinePipeline
from tactile_slam.sim.episode import SimulationSettings, read_episode, simulate_episode


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--object", default="seed", help="catalogue object")
    p.add_argument("--kind", default="contact_loss", help="motion kind of the episode")
    p.add_argument("--frames", type=positive_int, default=300, help="episode length (the replay loops it)")
    p.add_argument("--replays", default="300,10500", help="comma-separated replay lengths in frames")
    p.add_argument("--rate", type=float, default=1.0, help="replay speed (1: the sensor's 25 Hz)")
    p.add_argument("--buffer-frames", type=positive_int, default=3)
    p.add_argument("--tracker-threads", type=positive_int, default=1, help="torch threads of the tracker process")
    p.add_argument("--backend-threads", type=positive_int, default=1, help="torch threads of the back-end process")
    p.add_argument("--offline-max-frames", type=int, default=3000,
                   help="run the offline comparison only on replays up to this length")
    p.add_argument("--seed", type=int, default=4)
    p.add_argument("--episode", default=None, help="use this episode folder instead of simulating one")


def accuracy(res: RunResult, gt: np.ndarray) -> dict:
    """Per-axis MAE (mm, degrees) of the main group's frames (the largest group: the rows
    of ``poses.npy``), in the frame of its first frame."""
    sel = np.isfinite(res.poses[:, 0, 0])
    if not sel.any():
        return {"n_frames": 0}
    first = int(np.nonzero(sel)[0][0])
    mae = per_axis_mae(res.poses, np.linalg.inv(gt[first]) @ gt, sel)
    mae["translation_mm"] = float(np.mean([mae[k] for k in ("x_mm", "y_mm", "z_mm")]))
    mae["rotation_deg"] = float(np.mean([mae[k] for k in ("rx_deg", "ry_deg", "rz_deg")]))
    mae["group_frames"] = int(sel.sum())
    return mae


ONLINE_KEYS = ("frames", "frames_read", "frames_dropped", "frames_late", "latency_ms", "keyframes",
               "keyframes_skipped_for_loops", "keyframes_skipped_fraction", "loops", "group_merges", "sessions",
               "groups", "loop_corrections", "backend_error", "wall_time_s", "timing_ms", "timing_ms_per_keyframe")


def run(args) -> Path:
    with tempfile.TemporaryDirectory() as tmp:
        ep = Path(args.episode) if args.episode else simulate_episode(
            Path(tmp) / "episode", SimulationSettings(object=args.object, kind=args.kind, frames=args.frames,
                                                      seed=args.seed))
        gt_once = read_episode(ep).object_T_sensor
        base = GradientSequence(ep / EPISODE_NPZ, fps=Config().sensor.fps)
        results = {"episode": {"object": args.object, "kind": args.kind, "frames": len(base), "seed": args.seed},
                   "rate": args.rate, "fps": base.fps, "buffer_frames": args.buffer_frames,
                   "tracker_threads": args.tracker_threads, "backend_threads": args.backend_threads,
                   "replays": {}}
        for length in [int(x) for x in args.replays.split(",") if x]:
            source = LoopedSource(base, length)
            gt = gt_once[np.arange(length) % len(gt_once)]
            opts = OnlineOptions(progress=False, mesh=False, rate=args.rate, buffer_frames=args.buffer_frames,
                                 tracker_threads=args.tracker_threads, backend_threads=args.backend_threads)
            t0 = time.perf_counter()
            on = OnlinePipeline(source, Config(), Path(tmp) / f"online_{length}", opts).run()
            entry = {"minutes": length / base.fps / 60, "online_wall_s": time.perf_counter() - t0}
            entry["online"] = {k: on.stats.get(k) for k in ONLINE_KEYS}
            entry["online"]["processed_fraction"] = on.stats["frames"] / length
            entry["online_accuracy"] = accuracy(on, gt)
            if length <= args.offline_max_frames:
                threads = torch.get_num_threads()
                torch.set_num_threads(args.tracker_threads + args.backend_threads)
                try:
                    off = OfflinePipeline(source, Config(), Path(tmp) / f"offline_{length}",
                                          RunOptions(progress=False, mesh=False)).run()
                finally:
                    torch.set_num_threads(threads)
                entry["offline_accuracy"] = accuracy(off, gt)
                entry["offline"] = {k: off.stats.get(k) for k in ("keyframes", "loops", "sessions", "groups",
                                                                   "fps", "wall_time_s")}
                a, b = entry["online_accuracy"], entry["offline_accuracy"]
                if a.get("n_frames") and b.get("n_frames"):
                    entry["online_over_offline"] = {k: a[k] / b[k] if b[k] > 0 else float("nan")
                                                    for k in ("translation_mm", "rotation_deg")}
            results["replays"][str(length)] = entry
            s = entry["online"]
            print(f"realtime {length} frames: {s['frames']} processed, {s['frames_dropped']} dropped, latency "
                  f"median {s['latency_ms']['median']:.1f} / p95 {s['latency_ms']['p95']:.1f} ms, "
                  f"{s['keyframes_skipped_for_loops']}/{s['keyframes']} keyframes skipped for loops")
    return write_json(args.out, "realtime", results)
