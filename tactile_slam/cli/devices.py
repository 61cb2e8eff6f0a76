"""The ``--device`` option shared by the commands: checked while parsing
(:func:`tactile_slam.config.resolve_device`), so that a device this machine lacks is a
one-line error, not a traceback from deep inside torch."""

from __future__ import annotations

import argparse

from tactile_slam.config import ConfigError, resolve_device

HELP = "cpu, cuda, cuda:N, or auto (cuda when present)"


def device_arg(value: str) -> str:
    """``argparse`` type around :func:`~tactile_slam.config.resolve_device`."""
    try:
        return resolve_device(value)
    except ConfigError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from exc


def add_device_argument(parser: argparse.ArgumentParser, help: str = HELP) -> None:
    parser.add_argument("--device", type=device_arg, default="cpu", help=help)
