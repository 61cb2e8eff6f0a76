"""bench pipeline: per-device medians of whole pipeline runs on one simulated episode."""

import json
import mmap
from pathlib import Path

import numpy as np
import pytest
import torch

from tactile_slam.bench import pipeline
from tactile_slam.bench.common import PeakMemory
from tactile_slam.cli.main import main
from tactile_slam.config import Config
from tactile_slam.io.dispatch import open_source
from tactile_slam.pipeline.offline import OfflinePipeline, RunOptions
from tactile_slam.sim.episode import SimulationSettings, simulate_episode


def test_summarise_takes_medians_per_stage():
    runs = [{"fps": f, "timing_ms": {"geometry": g, "tracking": 1.0}, "timing_ms_per_keyframe": None,
             "frames": 10, "keyframes": 2} for f, g in [(10.0, 3.0), (30.0, 1.0), (20.0, 2.0)]]
    s = pipeline.summarise(runs)
    assert s["fps_median"] == 20.0 and s["fps_runs"] == [10.0, 30.0, 20.0]
    assert s["timing_ms_median"] == {"geometry": 2.0, "tracking": 1.0}
    assert s["timing_ms_per_keyframe_median"] == {}
    assert s["outcomes"][0]["keyframes"] == 2 and s["outcomes"][0]["loops"] is None
    assert s["peak_rss_mb_median"] is None and s["rss_growth_mb_median"] is None  # not measured here
    runs = [{**r, "memory_mb": {"start": 100.0, "peak": p}} for r, p in zip(runs, [140.0, 120.0, 160.0])]
    s = pipeline.summarise(runs)
    assert s["peak_rss_mb_median"] == 140.0 and s["rss_growth_mb_median"] == 40.0
    assert s["rss_growth_mb_per_keyframe_median"] == 20.0


@pytest.mark.skipif(not Path("/proc/self/clear_refs").exists(), reason="needs Linux /proc")
def test_peak_memory_sees_a_transient_allocation():
    """The peak is the block's own: a buffer freed before the block ends counts, and an
    earlier peak (the previous block's) does not. The buffer is an anonymous map touched
    page by page: a malloc'd one can reuse pages the process already holds (the full
    suite did that), which rightly raises no peak."""
    with PeakMemory() as mem:
        buf = mmap.mmap(-1, 80_000_000)
        for offset in range(0, len(buf), mmap.PAGESIZE):
            buf[offset] = 1
        buf.close()
    assert mem.peak_mb - mem.start_mb > 70
    with PeakMemory() as quiet:
        pass
    assert quiet.peak_mb - quiet.start_mb < 20


def test_bench_pipeline_matches_a_direct_run(tmp_path):
    out = tmp_path / "pipeline.json"
    assert main(["bench", "pipeline", "--out", str(out), "--frames", "60", "--level", "gradients",
                 "--devices", "cpu", "--repeats", "2"]) == 0
    doc = json.loads(out.read_text())
    assert doc["benchmark"] == "pipeline" and "cores" in doc["machine"]
    res = doc["results"]
    assert set(res["devices"]) == {"cpu"} and res["same_outcome"] is True
    cpu = res["devices"]["cpu"]
    assert len(cpu["fps_runs"]) == 2 and cpu["fps_median"] > 0
    assert {"geometry", "tracking", "total"} <= set(cpu["timing_ms_median"])
    if Path("/proc/self/clear_refs").exists():
        assert all(m["peak"] >= m["start"] > 0 for m in cpu["memory_mb_runs"]) and cpu["peak_rss_mb_median"] > 0
    # the outcome is what the pipeline gives when run directly on the same episode
    cfg = Config()
    ep = simulate_episode(tmp_path / "ep", SimulationSettings(object="seed", kind="tracking", seed=0, frames=60,
                                                              level="gradients"), cfg)
    direct = OfflinePipeline(open_source(ep, cfg), cfg, tmp_path / "run",
                             RunOptions(progress=False, mesh=False)).run().stats
    assert cpu["outcomes"][0] == {k: direct.get(k) for k in pipeline.OUTCOME_KEYS}
    assert direct["frames"] == 60 and np.isfinite(direct["fps"])


@pytest.mark.skipif(torch.cuda.is_available(), reason="needs a machine without CUDA")
def test_cuda_without_cuda_is_refused_before_running(tmp_path, capsys):
    with pytest.raises(SystemExit):
        main(["bench", "pipeline", "--out", str(tmp_path / "p.json"), "--devices", "cuda"])
    assert "cuda" in capsys.readouterr().err.lower()
    assert not (tmp_path / "p.json").exists()


@pytest.mark.parametrize("option", ["--repeats", "--frames"])
def test_bad_repeats_is_an_error(tmp_path, capsys, option):
    with pytest.raises(SystemExit) as exc:
        main(["bench", "pipeline", "--out", str(tmp_path / "p.json"), option, "0", "--devices", "cpu"])
    assert exc.value.code == 2
    assert f"argument {option}: must be >= 1" in capsys.readouterr().err and not (tmp_path / "p.json").exists()


def test_a_device_named_twice_runs_once(tmp_path):
    out = tmp_path / "p.json"
    assert main(["bench", "pipeline", "--out", str(out), "--frames", "30", "--level", "gradients",
                 "--devices", "cpu", "cpu", "--repeats", "1"]) == 0
    assert len(json.loads(out.read_text())["results"]["devices"]["cpu"]["fps_runs"]) == 1
