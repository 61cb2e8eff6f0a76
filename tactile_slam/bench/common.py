"""Shared benchmark helpers: timing statistics, machine description, JSON output."""

from __future__ import annotations

import json
import os
import platform
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import torch


def machine_info() -> dict[str, Any]:
    """What the numbers were measured on."""
    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    info = {
        "cpu": cpu,
        "cores": os.cpu_count(),
        "torch_threads": torch.get_num_threads(),
        "python": platform.python_version(),
        "torch": torch.__version__,
        "platform": platform.platform(),
        "cuda": torch.cuda.get_device_name(0) if torch.cuda.is_available() else None,
        "load_average_1_5_15min": list(os.getloadavg()) if hasattr(os, "getloadavg") else None,
    }
    return info


def set_threads(threads: int | None) -> None:
    """Apply a bench's ``--threads``: ``None`` leaves torch's choice, below 1 is an error."""
    if threads is None:
        return
    if threads < 1:
        raise ValueError(f"--threads must be >= 1, got {threads}")
    torch.set_num_threads(threads)


def median_per_key(dicts: list[dict]) -> dict[str, float]:
    """Per-key median of numeric dicts, over the dicts that hold the key (NaN values
    are skipped too), e.g. the per-stage ``timing_ms`` of several runs."""
    keys = sorted({k for d in dicts for k in d})
    return {k: float(np.nanmedian([d.get(k, np.nan) for d in dicts])) for k in keys}


def timing_stats(samples_s: list[float] | np.ndarray) -> dict[str, float]:
    """Median, IQR, p95, mean in milliseconds from samples in seconds."""
    a = np.asarray(samples_s, dtype=np.float64) * 1000.0
    q25, q50, q75, q95 = np.percentile(a, [25, 50, 75, 95])
    return {"median_ms": float(q50), "iqr_ms": float(q75 - q25), "p95_ms": float(q95),
            "mean_ms": float(a.mean()), "n": int(a.size)}


def time_fn(fn: Callable[[], Any], repeats: int, warmup: int = 3, sync_cuda: bool = False) -> list[float]:
    """Wall-clock samples (s) of ``fn()`` after ``warmup`` calls."""
    for _ in range(warmup):
        fn()
    out = []
    for _ in range(repeats):
        if sync_cuda:
            torch.cuda.synchronize()
        t0 = time.perf_counter()
        fn()
        if sync_cuda:
            torch.cuda.synchronize()
        out.append(time.perf_counter() - t0)
    return out


def _status_mb(key: str) -> float | None:
    """A ``/proc/self/status`` memory line (``VmRSS``, ``VmHWM``) in MB; ``None`` where
    there is no such file (not Linux)."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith(key + ":"):
                return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    return None


class PeakMemory:
    """Peak resident memory of this process over a block, in MB (Linux).

    ``with PeakMemory() as mem: work()`` then ``mem.start_mb`` (resident at entry) and
    ``mem.peak_mb`` (the highest resident size during the block: the kernel's high-water
    mark, reset at entry by writing 5 to ``/proc/self/clear_refs``). The start is the
    high-water mark just after that reset, not a separate ``VmRSS`` read: the kernel's
    resident counters are batched per thread, and a separate read can land a few MB
    above the mark the peak is measured from. Both are ``None`` where that is not
    possible, so a benchmark still runs elsewhere.
    """

    def __enter__(self) -> "PeakMemory":
        self.start_mb = self.peak_mb = None
        try:
            Path("/proc/self/clear_refs").write_text("5")
        except OSError:
            return self
        self.start_mb = _status_mb("VmHWM")
        return self

    def __exit__(self, *exc) -> None:
        if self.start_mb is not None:  # the block's peak is at least what was resident when it began
            self.peak_mb = max(_status_mb("VmHWM"), self.start_mb)


def write_json(path: str | Path, name: str, results: dict[str, Any]) -> Path:
    """Write ``{"benchmark", "machine", "date", "results"}`` to ``path``."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    doc = {"benchmark": name, "date": time.strftime("%Y-%m-%dT%H:%M:%S"), "machine": machine_info(),
           "results": results}
    path.write_text(json.dumps(doc, indent=2))
    return path


def rendered_frames(renderer, builder, object_T_sensor: np.ndarray, index: np.ndarray | None = None,
                    batch: int = 32) -> Iterator:
    """Gradient-level frames of simulated sensor poses, rendered ``batch`` at a time.

    Args:
        renderer: a :class:`~tactile_slam.sim.renderer.GelRenderer`.
        builder: a :class:`~tactile_slam.geometry.frame.FrameBuilder`.
        object_T_sensor: ``(N, 4, 4)`` poses, metres.
        index: ``(N,)`` video indices stored in the frames (default ``0..N-1``).

    Yields:
        one single-image :class:`~tactile_slam.geometry.frame.Frame` per pose, owning its
        memory (a slice of a batch would keep the whole render batch alive).
    """
    index = np.arange(len(object_T_sensor)) if index is None else np.asarray(index)
    for a in range(0, len(object_T_sensor), batch):
        maps = renderer.render(object_T_sensor[a:a + batch])
        frames = builder.from_gradients(maps.gradients, maps.contact, index=torch.as_tensor(index[a:a + batch]))
        for j in range(len(frames)):
            yield frames[j].clone()
