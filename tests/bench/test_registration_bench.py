"""bench registration: a tiny end-to-end run on one object, and its argument checks."""

import argparse
import json

import pytest

from tactile_slam.bench import registration


def _args(tmp_path, *extra: str) -> argparse.Namespace:
    p = argparse.ArgumentParser()
    p.add_argument("--out", default=str(tmp_path / "registration.json"))
    registration.add_arguments(p)
    return p.parse_args(["--objects", "seed", "--repeats", "1", "--threads", "1", *extra])


def test_tiny_run_reports_every_method_and_the_sweep(tmp_path):
    out = registration.run(_args(tmp_path, "--fpfh-pairs", "0"))
    res = json.loads(out.read_text())["results"]
    assert out.with_suffix(".png").exists()
    methods = res["methods"]
    assert "fpfh_ransac_icp" not in methods  # --fpfh-pairs 0 skips it
    n = len(res["motions"])
    nf, icp = methods["normalflow"], methods["icp_point_to_plane"]
    assert nf["all"]["n_pairs"] == icp["all"]["n_pairs"] == n and set(nf["per_object"]) == {"seed"}
    # the seed is textured: NormalFlow lands on the simulated truth on most of the pairs
    assert nf["all"]["rot_err_deg_median"] < 0.1 and nf["all"]["trans_err_mm_median"] < 0.01
    assert nf["all"]["wrong_rate"] <= 0.5
    assert nf["time_per_pair"]["median_ms"] > 0 and nf["time_per_pair_prepared"]["median_ms"] > 0
    batched = res["batched_normalflow"]
    assert {"B=1", "B=8", "B=64", "B=64, one reference", "B=64, alternating: default",
            "B=64, alternating: whole batch (cpu_chunk_samples=0)",
            "B=64, alternating: no stall check (stall_check_iters=0)"} <= set(batched)
    # the stall check only stops pairs that fail anyway: the same pairs pass, in fewer iterations
    off = methods["normalflow_no_stall_check (stall_check_iters=0)"]["all"]["per_pair"]
    assert off["ok"] == nf["all"]["per_pair"]["ok"]
    with_check, without = batched["B=64, iterations summed: default, no stall check"]
    assert with_check <= without
    caps = {(s["n_samples"], s["max_iters"]) for s in res["sweep"]}
    assert caps == {(k, c) for k in (250, 500, 1000, 3000, "all") for c in (10, 20, 50)}


def test_bad_counts_are_refused_before_any_work(tmp_path, capsys):
    with pytest.raises(ValueError, match="fpfh-pairs"):
        registration.run(_args(tmp_path, "--fpfh-pairs", "-1"))
    with pytest.raises(SystemExit):  # a count below 1: refused while parsing
        _args(tmp_path, "--repeats", "0")
    assert "argument --repeats: must be >= 1" in capsys.readouterr().err
    assert not (tmp_path / "registration.json").exists()
