"""Pose-graph back end: full sparse solve, incremental updates, pypose.optim.LM for comparison.

Graphs are synthetic scans (:mod:`tactile_slam.posegraph.synthetic`): the sensor slides over a
20 mm sphere, loops join a keyframe to earlier coverage keyframes within 3 mm, as in GelSLAM.
Targets (issue 6): full solve of 5,000 keyframes / 15,000 edges <= 2 s; incremental update
<= 20 ms per keyframe amortised over a 5,000-keyframe scan. Process CPU time is reported next to
wall time: the solver runs on one thread, so on a shared machine CPU time estimates the wall
time a quiet machine would show.
"""

from __future__ import annotations

import argparse
import copy
import time
from pathlib import Path

import numpy as np
import torch

from tactile_slam.bench.common import timing_stats, write_json
from tactile_slam.cli.arguments import positive_int
from tactile_slam.posegraph import se3
from tactile_slam.posegraph.graph import PoseGraph
from tactile_slam.posegraph.incremental import IncrementalSolver
from tactile_slam.posegraph.reference import solve_pypose
from tactile_slam.posegraph.solver import solve
from tactile_slam.posegraph.synthetic import SyntheticScan, add_step, replay_steps, synthetic_scan


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--keyframes", type=positive_int, default=5000, help="keyframes of the large graph")
    p.add_argument("--edges", type=positive_int, default=15000, help="edges (odometry + loops) of the large graph")
    p.add_argument("--repeats", type=positive_int, default=3, help="timed full solves (each from the odometry start)")
    p.add_argument("--pypose-sizes", type=positive_int, nargs="*", default=[50, 500],
                   help="keyframes of the graphs timed with pypose.optim.LM (loops = keyframes / 2)")
    p.add_argument("--pypose-iters", type=positive_int, default=2, help="pypose.optim.LM iterations timed per size")
    p.add_argument("--pypose-time-limit", type=float, default=120.0, help="seconds allowed per pypose size")
    p.add_argument("--skip-incremental", action="store_true", help="skip the incremental replay")


def _errors(P: torch.Tensor, gt: torch.Tensor) -> dict[str, float]:
    P = se3.inverse(P[0]) @ P
    d = se3.log(se3.inverse(gt) @ P)
    return {"trans_mm_mean": float(d[:, :3].norm(dim=-1).mean() * 1e3),
            "rot_deg_mean": float(np.degrees(float(d[:, 3:].norm(dim=-1).mean())))}


def _full_solve(scan: SyntheticScan, repeats: int) -> dict:
    times, cpu, reports = [], [], []
    for _ in range(repeats):
        g = copy.deepcopy(scan.graph)
        t0, c0 = time.perf_counter(), time.process_time()
        rep = solve(g)
        times.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
        reports.append(rep)
    rep = reports[-1]
    return {"timing": timing_stats(times), "cpu_timing": timing_stats(cpu),
            "iterations": rep.iterations, "converged": rep.converged,
            "per_iteration_ms": 1e3 * float(np.median(times)) / max(rep.iterations, 1),
            "cost_initial": rep.cost_initial, "cost_final": rep.cost_final,
            "error_odometry": _errors(scan.graph.poses(), scan.gt), "error_solved": _errors(g.poses(), scan.gt)}


def _incremental(scan: SyntheticScan) -> dict:
    g = PoseGraph()
    inc = IncrementalSolver(g)
    per_kf, solved, regions = [], 0, []
    t_all, c_all = time.perf_counter(), time.process_time()
    for step in replay_steps(scan):
        t0 = time.perf_counter()
        add_step(g, step)
        rep = inc.update()
        per_kf.append(time.perf_counter() - t0)
        if not rep.skipped:
            solved += 1
            regions.append(rep.regions[-1])
    total, total_cpu = time.perf_counter() - t_all, time.process_time() - c_all
    before_final = g.poses()
    t0 = time.perf_counter()
    final = inc.finalize()
    final_s = time.perf_counter() - t0
    drift = (before_final[:, :3, 3] - g.poses()[:, :3, 3]).norm(dim=-1)
    n = len(per_kf)
    return {"amortised_ms_per_keyframe": 1e3 * total / n, "amortised_cpu_ms_per_keyframe": 1e3 * total_cpu / n,
            "per_keyframe": timing_stats(per_kf),
            "keyframes_solved": solved, "keyframes_skipped": n - solved,
            "region_size_median": float(np.median(regions)) if regions else 0.0,
            "region_size_max": int(max(regions)) if regions else 0,
            "max_distance_to_batch_optimum_mm": float(drift.max() * 1e3),
            "final_full_solve_s": final_s, "final_full_solve_iterations": final.iterations,
            "error_incremental": _errors(before_final, scan.gt)}


def _sphere_radius(n: int) -> float:
    """Object radius keeping the keyframe density of 5,000 keyframes on a 20 mm sphere."""
    return max(0.004, 0.02 * (n / 5000) ** 0.5)


def _pypose_vs_sparse(n: int, iters: int, time_limit: float) -> dict:
    scan = synthetic_scan(n, n // 2, seed=3, radius_m=_sphere_radius(n), coverage_spacing_m=0.0)
    g = copy.deepcopy(scan.graph)
    t0 = time.perf_counter()
    rep = solve(g, max_iters=iters)
    sparse_s = time.perf_counter() - t0
    ref = solve_pypose(copy.deepcopy(scan.graph), max_iters=iters, time_limit_s=time_limit)
    return {"keyframes": n, "edges": scan.graph.num_edges,
            "pypose_lm_per_iteration": timing_stats(ref["step_s"]),
            "sparse_lm_per_iteration_ms": 1e3 * sparse_s / max(rep.iterations, 1),
            "sparse_iterations": rep.iterations, "pypose_iterations": ref["iterations"]}


def run(args) -> Path:
    n_loops = args.edges - (args.keyframes - 1)
    if n_loops < 0:
        raise ValueError(f"--edges must be at least --keyframes - 1 = {args.keyframes - 1}")
    scan = synthetic_scan(args.keyframes, n_loops, seed=0, radius_m=_sphere_radius(args.keyframes))
    results = {"graph": {"keyframes": args.keyframes, "edges": scan.graph.num_edges, "loops": n_loops,
                         "targets": {"full_solve_s": 2.0, "incremental_ms_per_keyframe": 20.0}},
               "full_solve": _full_solve(scan, args.repeats)}
    print(f"full solve: median {results['full_solve']['timing']['median_ms']:.0f} ms wall, "
          f"{results['full_solve']['cpu_timing']['median_ms']:.0f} ms CPU, "
          f"{results['full_solve']['iterations']} iterations")
    if not args.skip_incremental:
        results["incremental"] = _incremental(scan)
        inc = results["incremental"]
        print(f"incremental: {inc['amortised_ms_per_keyframe']:.1f} ms/keyframe amortised wall, "
              f"{inc['amortised_cpu_ms_per_keyframe']:.1f} ms CPU")
    results["pypose_comparison"] = [_pypose_vs_sparse(n, args.pypose_iters, args.pypose_time_limit)
                                    for n in args.pypose_sizes]
    for c in results["pypose_comparison"]:
        print(f"{c['keyframes']} keyframes: pypose.optim.LM {c['pypose_lm_per_iteration']['median_ms']:.0f} ms"
              f"/iteration, sparse LM {c['sparse_lm_per_iteration_ms']:.1f} ms/iteration")
    return write_json(args.out, "posegraph", results)
