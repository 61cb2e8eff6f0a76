"""The ``--device`` option shared by the commands: checked while parsing, so that a
device this machine lacks is a one-line error, not a traceback from deep inside torch."""

from __future__ import annotations

import argparse

import torch

HELP = "cpu, cuda, cuda:N, or auto (cuda when present)"


def device_arg(value: str) -> str:
    """``argparse`` type: ``"auto"`` -> ``"cuda"`` if available else ``"cpu"``; any
    other name must be a torch device this machine has."""
    if value == "auto":
        return "cuda" if torch.cuda.is_available() else "cpu"
    try:
        dev = torch.device(value)
    except RuntimeError as exc:
        raise argparse.ArgumentTypeError(f"unknown device {value!r} (use {HELP})") from exc
    if dev.type == "cuda":
        if not torch.cuda.is_available():
            build = "a CPU-only build" if torch.version.cuda is None else f"CUDA {torch.version.cuda}, no GPU visible"
            raise argparse.ArgumentTypeError(f"{value}: CUDA is not available (torch {torch.__version__}, {build})")
        if dev.index is not None and dev.index >= torch.cuda.device_count():
            raise argparse.ArgumentTypeError(f"{value}: only {torch.cuda.device_count()} CUDA device(s)")
    elif dev.type != "cpu":
        raise argparse.ArgumentTypeError(f"unsupported device {value!r} (use {HELP})")
    return value


def add_device_argument(parser: argparse.ArgumentParser, help: str = HELP) -> None:
    parser.add_argument("--device", type=device_arg, default="cpu", help=help)
