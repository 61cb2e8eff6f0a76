"""``tactile-slam`` entry point. Each sub-command lives in its own module under
``tactile_slam.cli`` and exposes ``register(subparsers)``; it sets ``func`` on its
parser, which receives the parsed arguments and returns an exit code."""

from __future__ import annotations

import argparse
import faulthandler
import importlib
import sys

COMMAND_MODULES = (
    "tactile_slam.cli.demo",
    "tactile_slam.cli.run",
    "tactile_slam.cli.bench",
    "tactile_slam.cli.calibrate",
    "tactile_slam.cli.simulate",
    "tactile_slam.cli.eval",
    "tactile_slam.cli.record",
    "tactile_slam.cli.live",
)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="tactile-slam", description="Tactile SLAM for GelSight-type sensors.")
    sub = parser.add_subparsers(dest="command", required=True)
    for name in COMMAND_MODULES:
        importlib.import_module(name).register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    # a crash inside a native library (Open3D, OpenCV) prints the Python stack that led
    # there instead of a bare "Segmentation fault"
    if not faulthandler.is_enabled():
        faulthandler.enable()
    args = build_parser().parse_args(argv)
    try:
        rc = args.func(args)
        return rc if isinstance(rc, int) else 0
    except KeyboardInterrupt:  # the pipelines keep what they computed before it
        print(f"tactile-slam {args.command}: interrupted", file=sys.stderr)
        return 130
    except (ValueError, OSError, RuntimeError) as exc:
        # Errors carry a message that names the problem (an OSError its path: a full disk,
        # a folder removed during the run); show it without a traceback.
        print(f"tactile-slam {args.command}: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
