"""Simulator speed: gel rendering frames per second per object, and end-to-end episodes."""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

from tactile_slam.bench.common import time_fn, timing_stats, write_json
from tactile_slam.cli.arguments import positive_int
from tactile_slam.cli.devices import add_device_argument
from tactile_slam.config import Config
from tactile_slam.sim.episode import SimulationSettings, simulate_episode
from tactile_slam.sim.motions import make_motion
from tactile_slam.sim.objects import OBJECTS, make_object
from tactile_slam.sim.renderer import GelRenderer


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--objects", default=",".join(sorted(OBJECTS)), help="comma-separated catalogue objects")
    p.add_argument("--batch", type=positive_int, default=32, help="frames rendered per call")
    p.add_argument("--repeats", type=positive_int, default=5, help="timed batches per object")
    p.add_argument("--episode-objects", default="seed,lime",
                   help="objects for the end-to-end 520-frame tracking episode timing ('' to skip)")
    add_device_argument(p)


def run(args) -> Path:
    cfg = Config()
    results: dict = {"device": args.device, "image_size": list(cfg.sensor.shape), "batch": args.batch,
                     "per_object": {}, "episode_tracking_520": {}}
    for name in [n for n in args.objects.split(",") if n]:
        t0 = time.perf_counter()
        mesh = make_object(name)
        build_s = time.perf_counter() - t0
        renderer = GelRenderer(mesh, cfg, device=args.device)
        poses = make_motion(renderer, "tracking", n_frames=10 + args.batch * 4, seed=0).object_T_sensor[10:]
        batches = [poses[k * args.batch:(k + 1) * args.batch] for k in range(4)]
        counter = iter(range(10**9))
        samples = time_fn(lambda: renderer.render(batches[next(counter) % 4]), args.repeats, warmup=1,
                          sync_cuda=args.device.startswith("cuda"))
        st = timing_stats(samples)
        results["per_object"][name] = {
            "triangles": len(mesh.triangles), "mesh_build_s": build_s,
            "fps": args.batch / (st["median_ms"] / 1000.0), "ms_per_frame": st["median_ms"] / args.batch,
            "batch_timing": st,
        }
        print(f"{name:8s} {results['per_object'][name]['fps']:6.1f} frames/s "
              f"({len(mesh.triangles)} triangles, mesh {build_s:.1f} s)")
    for name in [n for n in args.episode_objects.split(",") if n]:
        with tempfile.TemporaryDirectory() as tmp:
            t0 = time.perf_counter()
            simulate_episode(tmp, SimulationSettings(object=name, kind="tracking", frames=520), cfg, device=args.device)
            wall = time.perf_counter() - t0
        results["episode_tracking_520"][name] = {"wall_s": wall, "frames_per_s": 520 / wall}
        print(f"{name:8s} 520-frame tracking episode (gradient level, incl. mesh, motion, files): {wall:.1f} s")
    results["median_fps_over_objects"] = float(np.median([v["fps"] for v in results["per_object"].values()])) \
        if results["per_object"] else None
    return write_json(args.out, "render", results)
