"""Value types of the commands' options, checked while parsing: a bad output location or a
bad number is a one-line error before any work starts, not a traceback after a run whose
results then have nowhere to go.

Each is an ``argparse`` ``type=`` callable; ``argparse`` turns the
:class:`argparse.ArgumentTypeError` into ``tactile-slam CMD: error: argument --out: ...``.
"""

from __future__ import annotations

import argparse
import math
import os
from pathlib import Path

STDOUT = "-"


def _writable_parent(path: Path, what: str) -> None:
    """The nearest existing ancestor of ``path`` must be a folder this process can create
    entries in (the missing folders between are created later)."""
    parent = path.absolute().parent
    while not parent.exists():
        parent = parent.parent
    if not parent.is_dir():
        raise argparse.ArgumentTypeError(f"{what} {path}: {parent} is a file, not a folder")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise argparse.ArgumentTypeError(f"{what} {path}: no permission to write in {parent}")


def output_folder(value: str) -> str:
    """A folder to write into: missing (created later) or an existing, writable folder;
    never an existing file. Returns ``value`` unchanged (commands record it as given)."""
    path = Path(value)
    if not value:
        raise argparse.ArgumentTypeError("output folder: empty path")
    if path.exists():
        if not path.is_dir():
            raise argparse.ArgumentTypeError(f"output folder {path} is an existing file")
        if not os.access(path, os.W_OK | os.X_OK):
            raise argparse.ArgumentTypeError(f"output folder {path}: no permission to write in it")
    else:
        _writable_parent(path, "output folder")
    return value


def output_file(value: str) -> str:
    """A file to write: missing or an existing file (replaced), in a folder that exists or
    can be created; never an existing folder. Returns ``value`` unchanged."""
    path = Path(value)
    if not value:
        raise argparse.ArgumentTypeError("output file: empty path")
    if path.is_dir():
        raise argparse.ArgumentTypeError(f"output file {path} is an existing folder")
    if path.exists() and not os.access(path, os.W_OK):
        raise argparse.ArgumentTypeError(f"output file {path}: no permission to write it")
    _writable_parent(path, "output file")
    return value


def output_file_or_stdout(value: str) -> str:
    """:func:`output_file`, or ``-`` for standard output."""
    return value if value == STDOUT else output_file(value)


def positive_int(value: str) -> int:
    """An integer >= 1 (thread counts, frame counts)."""
    try:
        n = int(value)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer, got {value!r}") from None
    if n < 1:
        raise argparse.ArgumentTypeError(f"must be >= 1, got {n}")
    return n


def positive_int_list(value: str) -> tuple[int, ...]:
    """Comma-separated integers >= 1, e.g. layer sizes ``32,32,32``."""
    try:
        return tuple(positive_int(v.strip()) for v in value.split(","))
    except argparse.ArgumentTypeError as exc:
        raise argparse.ArgumentTypeError(f"expected comma-separated integers >= 1, got {value!r} ({exc})") from None


def non_negative_float(value: str) -> float:
    """A finite number >= 0 (rates, periods)."""
    try:
        x = float(value)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {value!r}") from None
    if not math.isfinite(x) or x < 0:
        raise argparse.ArgumentTypeError(f"must be a finite number >= 0, got {value}")
    return x
