"""``tactile-slam bench NAME``: run a benchmark module ``tactile_slam.bench.NAME``.

Each benchmark module exposes ``add_arguments(parser)`` and ``run(args) -> Path`` (the
JSON it wrote)."""

from __future__ import annotations

import importlib

from tactile_slam.cli.arguments import output_file

BENCHMARKS = ("calibration", "geometry", "io", "labels", "loops", "pipeline", "posegraph", "reconstruction", "realtime",
              "registration", "render", "tracking")


def register(sub) -> None:
    p = sub.add_parser("bench", help="run a benchmark and write JSON with median timings")
    bsub = p.add_subparsers(dest="benchmark", required=True)
    for name in BENCHMARKS:
        mod = importlib.import_module(f"tactile_slam.bench.{name}")
        bp = bsub.add_parser(name, help=(mod.__doc__ or "").strip().splitlines()[0])
        bp.add_argument("--out", default=f"benchmarks/{name}.json", type=output_file, help="JSON output path")
        mod.add_arguments(bp)
        bp.set_defaults(func=mod.run)
