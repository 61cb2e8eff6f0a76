"""Value types of the commands' options, checked while parsing: a bad output location or a
bad number is a one-line error before any work starts, not a traceback after a run whose
results then have nowhere to go.

Each is an ``argparse`` ``type=`` callable; ``argparse`` turns the
:class:`argparse.ArgumentTypeError` into ``tactile-slam CMD: error: argument --out: ...``.
"""

from __future__ import annotations

import argparse
import math

from tactile_slam.pipeline.outputs import OutputPathError, check_output_file, check_output_folder

STDOUT = "-"


def _checked(check, value: str) -> str:
    try:
        check(value)
    except OutputPathError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None
    return value


def output_folder(value: str) -> str:
    """:func:`~tactile_slam.pipeline.outputs.check_output_folder`; returns ``value`` unchanged
    (commands record it as given)."""
    return _checked(check_output_folder, value)


def output_file(value: str) -> str:
    """:func:`~tactile_slam.pipeline.outputs.check_output_file`; returns ``value`` unchanged."""
    return _checked(check_output_file, value)


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
