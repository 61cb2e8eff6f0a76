"""``tactile-slam run SCAN --out DIR``: the offline pipeline on a recording."""

from __future__ import annotations

import sys
from pathlib import Path

import torch

from tactile_slam.cli.arguments import output_folder, positive_int
from tactile_slam.cli.devices import add_device_argument
from tactile_slam.cli.live import (add_online_arguments, caveats, message_stream, online_only_given, online_options,
                                   report, run_online)
from tactile_slam.config import load_config
from tactile_slam.io.dispatch import open_source
from tactile_slam.pipeline.offline import METHODS, OfflinePipeline, RunOptions
from tactile_slam.pipeline.online import OnlinePipeline
from tactile_slam.pipeline.visualizer import KeyframePanels, NullVisualizer


def register(sub) -> None:
    p = sub.add_parser("run", help="track a recorded scan, video or gradient-map sequence")
    p.add_argument("scan", help="recorded-scan folder, video file, image folder or gradient-map sequence")
    p.add_argument("--out", required=True, type=output_folder, help="output folder")
    p.add_argument("--config", default=None, help="YAML config (ours or GelSLAM's) or a preset name")
    add_device_argument(p)
    p.add_argument("--method", default="gelslam", choices=METHODS,
                   help="gelslam (full system, default), ablations gs-onlysift/gs-onlynf/gs-imagesift, "
                        "nf-kf (tracker only) or nf (frame-to-frame NormalFlow)")
    p.add_argument("--model", default=None, help="calibration model file (default: the sensor's packaged model)")
    p.add_argument("--batch-size", type=positive_int, default=8, help="frames per geometry batch")
    p.add_argument("--resize", action="store_true",
                   help="resize frames of another size to the sensor's working size (default: refuse them)")
    p.add_argument("--keyframe-panels", action="store_true", help="write a geometry picture per keyframe")
    p.add_argument("--no-mesh", action="store_true", help="poses only: skip fusion and meshing")
    p.add_argument("--no-progress", action="store_true")
    p.add_argument("--online", action="store_true", help="real-time replay with loop closure in parallel (see live)")
    add_online_arguments(p)
    p.set_defaults(func=run)


def run(args) -> int:
    offline_extras = [] if args.online else online_only_given(args)
    if offline_extras:
        raise ValueError(f"{', '.join(offline_extras)}: used only with --online (add it, or drop them)")
    if args.threads is not None and not args.online:  # online, OnlinePipeline sets the tracker's
        torch.set_num_threads(args.threads)
    config = load_config(args.config) if args.config else None
    source = open_source(args.scan, config, resize=args.resize)
    config = config or getattr(source, "config", None) or load_config(None)
    out = Path(args.out)
    vis = KeyframePanels(out / "keyframes") if args.keyframe_panels else NullVisualizer()
    if args.online:
        messages = message_stream(args)
        s = run_online(OnlinePipeline(source, config, out, online_options(args), vis), messages).stats
        report(s, out, messages)
    else:
        messages = sys.stdout
        options = RunOptions(method=args.method, device=args.device, model=args.model,
                             batch_size=args.batch_size, progress=not args.no_progress, mesh=not args.no_mesh)
        s = OfflinePipeline(source, config, out, options, vis).run().stats
        loops = f", {s['loops']} loops, {s['groups']} groups" if "loops" in s else ""
        print(f"run: {s['frames']} frames, {s['contact_frames']} in contact, {s['keyframes']} keyframes, "
              f"{s['sessions']} sessions{loops}, {s['fps']:.1f} frames/s -> {out}")
        for line in caveats(s):
            print(f"run: {line}")
    if not s["completed"]:  # only an interrupt returns here (Ctrl+C); other errors raise
        print(f"run: interrupted ({s.get('error', 'KeyboardInterrupt')}); the outputs hold the frames before it",
              file=messages)
        return 130
    return 0
