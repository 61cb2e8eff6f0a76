"""``tactile-slam live --out DIR [--camera SPEC]``: the online pipeline on a live sensor.

Ctrl+C ends the run; everything computed so far is saved. The options shared with
``tactile-slam run SCAN --online`` are defined here (:func:`add_online_arguments`), and
so is how both print: with ``--jsonl -`` standard output carries the pose events' JSON
lines only, and every message goes to standard error (:func:`message_stream`).
"""

from __future__ import annotations

import contextlib
import sys
from pathlib import Path
from typing import TextIO

from tactile_slam.cli.arguments import (STDOUT, non_negative_float, output_file_or_stdout, output_folder,
                                        positive_int)
from tactile_slam.cli.devices import add_device_argument
from tactile_slam.config import load_config
from tactile_slam.io.dispatch import CAMERA_PREFIX, open_source
from tactile_slam.pipeline.offline import METHODS, RunResult
from tactile_slam.pipeline.online import OnlineOptions, OnlinePipeline
from tactile_slam.pipeline.visualizer import KeyframePanels, NullVisualizer


ONLINE_ONLY = ("--rate", "--buffer-frames", "--no-skip-loops", "--preview-every", "--jsonl")
"""Options of the online pipeline that an offline ``run`` has no use for."""


def add_online_arguments(p) -> None:
    """Options of the online pipeline (``live`` and ``run --online``). Their defaults are
    ``None`` (resolved by :func:`online_options`), so ``run`` can tell which were given
    (:func:`online_only_given`)."""
    p.add_argument("--rate", type=non_negative_float, default=None,
                   help="replay speed as a multiple of the recording's frame rate (default 1); 0: lossless, as fast "
                        "as tracking goes (recordings only)")
    p.add_argument("--buffer-frames", type=positive_int, default=None,
                   help="frames that may wait before the oldest is dropped (default 3)")
    p.add_argument("--no-skip-loops", action="store_true", default=None,
                   help="detect loops for every keyframe even when the back end falls behind")
    p.add_argument("--preview-every", type=non_negative_float, default=None, metavar="S",
                   help="write preview/preview.ply and preview.png at most every S seconds")
    p.add_argument("--jsonl", type=output_file_or_stdout, default=None,
                   help="pose events as JSON lines to this file ('-': stdout)")
    p.add_argument("--threads", type=positive_int, default=None,
                   help="torch threads of this process: the tracker (online) or the whole run (run without "
                        "--online); default: unchanged")


def online_only_given(args) -> list[str]:
    """The :data:`ONLINE_ONLY` options set on the command line."""
    return [opt for opt in ONLINE_ONLY if getattr(args, opt[2:].replace("-", "_")) is not None]


def online_options(args) -> OnlineOptions:
    """:class:`OnlineOptions` of the parsed arguments (its own defaults where not given)."""
    given = {}
    if args.rate is not None:
        given["rate"] = args.rate if args.rate > 0 else None
    if args.buffer_frames is not None:
        given["buffer_frames"] = args.buffer_frames
    return OnlineOptions(
        method=args.method, device=args.device, model=args.model, progress=not args.no_progress,
        mesh=not args.no_mesh, skip_loops=not args.no_skip_loops, preview_every_s=args.preview_every,
        jsonl=args.jsonl, tracker_threads=args.threads, **given)


def message_stream(args) -> TextIO:
    """Where an online command's messages go: standard error when ``--jsonl -`` gives
    standard output to the pose events, else standard output."""
    return sys.stderr if args.jsonl == STDOUT else sys.stdout


def run_online(pipeline: OnlinePipeline, messages: TextIO) -> RunResult:
    """``pipeline.run()``, with whatever the run prints (an earlier run's outputs
    replaced, a mesh skipped) sent to ``messages``; the pose stream keeps the standard
    output it opened when the pipeline was built."""
    with contextlib.redirect_stdout(messages):
        return pipeline.run()


def register(sub) -> None:
    p = sub.add_parser("live", help="track a live sensor with loop closure in parallel (Ctrl+C saves and stops)")
    p.add_argument("--out", required=True, type=output_folder, help="output folder")
    p.add_argument("--camera", default="GelSight Mini", help="device index or a V4L2 name it contains")
    p.add_argument("--config", default=None, help="YAML config (ours or GelSLAM's) or a preset name")
    add_device_argument(p)
    p.add_argument("--method", default="gelslam", choices=[m for m in METHODS if m != "gs-imagesift"])
    p.add_argument("--model", default=None, help="calibration model file (default: the sensor's packaged model)")
    p.add_argument("--keyframe-panels", action="store_true", help="write a geometry picture per keyframe")
    p.add_argument("--no-mesh", action="store_true", help="poses only: skip fusion and meshing")
    p.add_argument("--no-progress", action="store_true")
    add_online_arguments(p)
    p.set_defaults(func=run)


def run(args) -> int:
    config = load_config(args.config)
    out = Path(args.out)
    messages = message_stream(args)
    with open_source(f"{CAMERA_PREFIX}{args.camera}", config) as source:
        vis = KeyframePanels(out / "keyframes") if args.keyframe_panels else NullVisualizer()
        result = run_online(OnlinePipeline(source, config, out, online_options(args), vis), messages)
    report(result.stats, out, messages)
    return 0  # Ctrl+C is how a live run ends


def report(s: dict, out: Path, messages: TextIO) -> None:
    """The online run's summary, a dead back end and the :func:`caveats`, to ``messages``."""
    lat = s["latency_ms"]
    print(f"online: {s['frames']} frames ({s['frames_dropped']} dropped), {s['keyframes']} keyframes "
          f"({s['keyframes_skipped_for_loops']} without loop detection), {s.get('loops', 0)} loops, "
          f"latency median {lat['median']:.0f} ms / p95 {lat['p95']:.0f} ms, stopped by {s['stopped_by']} -> {out}",
          file=messages)
    if s.get("backend_error"):
        print(f"warning: {s['backend_error']}", file=messages)
    for line in caveats(s):
        print(f"online: {line}", file=messages)


def caveats(s: dict) -> list[str]:
    """What a run's statistics say the user should know about its poses: sessions broken
    inside a contact, keyframes whose depth is a guess."""
    out = []
    if s.get("registration_breaks"):
        out.append(f"{s['registration_breaks']} of the {s['sessions']} sessions began inside a contact because "
                   "registration failed (too little texture, or too fast a motion)")
    if s.get("keyframes_depth_unknown"):
        out.append(f"{s['keyframes_depth_unknown']} keyframes saw no undeformed gel (the object covered it): "
                   "their press depth, so their z, is a guess (keyframes.json depth_known)")
    return out
