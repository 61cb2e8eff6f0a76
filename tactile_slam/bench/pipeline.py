"""Whole offline pipeline per device: frames per second and per-stage medians of one simulated episode.

Simulates one episode (``--object``, ``--kind``, ``--level``), then runs the offline
pipeline on it once per device per repeat, the devices taking turns within each repeat so
that a drift of the machine's speed affects them alike. Reports, per device, the median over
the repeats of ``stats.json``'s ``fps``, ``timing_ms`` (per-frame stage medians) and
``timing_ms_per_keyframe``, the peak resident memory of each run and its growth over the
memory at the run's start (per keyframe too: keyframes are what a long scan accumulates),
and whether every run ended with the same keyframes, sessions, loops and groups (the
devices should agree).
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import numpy as np
import torch

from tactile_slam.bench.common import PeakMemory, median_per_key, write_json
from tactile_slam.cli.arguments import positive_int
from tactile_slam.cli.devices import device_arg
from tactile_slam.config import Config, resolve_device
from tactile_slam.io.dispatch import open_source
from tactile_slam.pipeline.offline import OfflinePipeline, RunOptions
from tactile_slam.sim.episode import SimulationSettings, simulate_episode

OUTCOME_KEYS = ("frames", "contact_frames", "keyframes", "sessions", "loops", "groups")


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--object", default="seed", help="simulator object")
    p.add_argument("--kind", default="tracking", help="motion kind of the episode")
    p.add_argument("--frames", type=positive_int, default=300, help="episode length")
    p.add_argument("--level", default="image", choices=("image", "gradients"), help="input level")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--devices", nargs="+", type=device_arg, default=None,
                   help="devices to compare (default: cpu, and cuda when present)")
    p.add_argument("--method", default="gelslam", help="pipeline method (see tactile-slam run --method)")
    p.add_argument("--mesh", action="store_true", help="also reconstruct (default: poses only)")
    p.add_argument("--repeats", type=positive_int, default=3, help="runs per device")


def summarise(runs: list[dict]) -> dict:
    """Medians over one device's runs of the ``stats.json`` timings and of the memory
    (``memory_mb``: ``start`` and ``peak`` resident MB per run, added by :func:`run`;
    ``None`` where it could not be measured)."""
    mem = [r.get("memory_mb") or {} for r in runs]
    measured = [(m["peak"] - m["start"], r.get("keyframes")) for m, r in zip(mem, runs) if m.get("peak") is not None]
    growth = [g for g, _ in measured]
    per_kf = [g / k for g, k in measured if k]
    median = lambda v: float(np.median(v)) if v else None  # noqa: E731
    return {"fps_median": float(np.median([r["fps"] for r in runs])),
            "fps_runs": [r["fps"] for r in runs],
            "timing_ms_median": median_per_key([r["timing_ms"] for r in runs]),
            "timing_ms_per_keyframe_median": median_per_key([r.get("timing_ms_per_keyframe") or {} for r in runs]),
            "peak_rss_mb_median": median([m["peak"] for m in mem if m.get("peak") is not None]),
            "rss_growth_mb_median": median(growth),
            "rss_growth_mb_per_keyframe_median": median(per_kf),
            "memory_mb_runs": mem,
            "outcomes": [{k: r.get(k) for k in OUTCOME_KEYS} for r in runs]}


def run(args) -> Path:
    if args.repeats < 1 or args.frames < 1:
        raise ValueError(f"--repeats and --frames must be >= 1, got {args.repeats} and {args.frames}")
    devices = list(dict.fromkeys(args.devices or ["cpu", resolve_device("auto")]))  # in order, once each
    cfg = Config()
    runs: dict[str, list[dict]] = {d: [] for d in devices}
    with tempfile.TemporaryDirectory() as tmp:
        episode = simulate_episode(Path(tmp) / "episode", SimulationSettings(
            object=args.object, kind=args.kind, seed=args.seed, frames=args.frames, level=args.level), cfg)
        for i in range(args.repeats):
            for d in devices:
                options = RunOptions(method=args.method, device=d, progress=False, mesh=args.mesh)
                source = open_source(episode, cfg)  # opened first: a whole-file input is not the run's growth
                with PeakMemory() as mem:
                    result = OfflinePipeline(source, cfg, Path(tmp) / f"run_{d}_{i}".replace(":", "_"), options).run()
                runs[d].append({**result.stats, "memory_mb": {"start": mem.start_mb, "peak": mem.peak_mb}})
    per_device = {d: summarise(r) for d, r in runs.items()}
    outcomes = [o for s in per_device.values() for o in s["outcomes"]]
    results = {"episode": {"object": args.object, "kind": args.kind, "frames": args.frames, "level": args.level,
                           "seed": args.seed},
               "method": args.method, "mesh": args.mesh, "repeats": args.repeats,
               "torch_threads": torch.get_num_threads(), "devices": per_device,
               "same_outcome": all(o == outcomes[0] for o in outcomes)}
    return write_json(args.out, "pipeline", results)
