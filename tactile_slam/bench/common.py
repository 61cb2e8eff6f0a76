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
    from tactile_slam.geometry.frame import Frame

    index = np.arange(len(object_T_sensor)) if index is None else np.asarray(index)
    for a in range(0, len(object_T_sensor), batch):
        maps = renderer.render(object_T_sensor[a:a + batch])
        frames = builder.from_gradients(maps.gradients, maps.contact, index=torch.as_tensor(index[a:a + batch]))
        for j in range(len(frames)):
            yield Frame.cat([frames[j]])
