"""Incremental updates replayed over a synthetic scan against the batch solution."""

from __future__ import annotations

import copy

import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.csgraph as csgraph
import torch

from tactile_slam.config import PoseGraphConfig
from tactile_slam.posegraph.graph import PoseGraph
from tactile_slam.posegraph.incremental import IncrementalSolver, _HopLevels
from tactile_slam.posegraph.solver import solve
from tactile_slam.posegraph.synthetic import add_step, replay_steps, synthetic_scan


def _replay(scan, config=None):
    """Add keyframes one by one (odometry, then loops ending at them), updating after each."""
    g = PoseGraph()
    inc = IncrementalSolver(g, config)
    reports = []
    for step in replay_steps(scan):
        add_step(g, step)
        reports.append(inc.update())
    return g, inc, reports


@pytest.fixture(scope="module")
def scan():
    return synthetic_scan(80, 60, seed=21, radius_m=0.005)


def test_tracks_batch_solution(scan):
    g, inc, reports = _replay(scan)
    assert reports[0].skipped  # the first prior holds at identity
    no_loop = [r for t, r in enumerate(reports) if t > 0 and r.new_cost == 0.0]
    assert no_loop and all(r.skipped for r in no_loop)  # odometry-only keyframes cost nothing
    assert any(not r.skipped and r.regions[0] < 80 for r in reports)  # local solves happen
    batch = copy.deepcopy(scan.graph)
    solve(batch)
    drift = (g.poses()[:, :3, 3] - batch.poses()[:, :3, 3]).norm(dim=-1).max()
    assert drift < 5e-5  # 0.05 mm from the batch optimum before any final solve
    inc.finalize()
    assert torch.allclose(g.poses(), batch.poses(), atol=1e-7)


def test_nothing_new_is_a_no_op(scan):
    g = copy.deepcopy(scan.graph)
    inc = IncrementalSolver(g)
    inc.update()
    rep = inc.update()
    assert rep.skipped and rep.regions == []


def test_removed_prior_triggers_solve():
    g = PoseGraph()
    g.add_nodes([0, 1], torch.eye(4, dtype=torch.float64).expand(2, 4, 4))
    g.add_prior(0)
    g.add_prior(1)
    g.add_between(0, 1, torch.eye(4))
    inc = IncrementalSolver(g, PoseGraphConfig(incremental_window=1))
    inc.update()
    g.remove_prior(1)
    rep = inc.update()
    assert not rep.skipped and rep.regions


@pytest.mark.parametrize("size", [1, 5, 40, 1000])
def test_hop_levels_match_shortest_paths(size):
    """The breadth-first region equals the one read off scipy's hop distances: every row
    within the smallest radius holding ``size`` rows (all reachable ones if fewer), and the
    rows one hop beyond; rows in another component are never reached."""
    gen = np.random.default_rng(4)
    n = 120
    a, b = gen.integers(0, 100, 200), gen.integers(0, 100, 200)  # rows 100-119: a separate chain
    a, b = np.concatenate([a, np.arange(100, 119)]), np.concatenate([b, np.arange(101, 120)])
    adjacency = [[] for _ in range(n)]
    for i, j in zip(a.tolist(), b.tolist()):
        adjacency[i].append(j)
        adjacency[j].append(i)
    seeds = [3, 17, 3]
    dist = csgraph.dijkstra(sp.coo_matrix((np.ones(a.size), (a, b)), shape=(n, n)).tocsr(), directed=False,
                            indices=sorted(set(seeds)), unweighted=True, min_only=True)
    levels = np.sort(dist[np.isfinite(dist)])
    radius = levels[min(size, levels.size) - 1]
    rows, boundary = _HopLevels(adjacency, seeds).region(size)
    assert rows.tolist() == np.nonzero(dist <= radius)[0].tolist()
    assert boundary.tolist() == np.nonzero(dist == radius + 1)[0].tolist()
    assert (rows < 100).all()
