"""Sparse LM on synthetic graphs: ground truth, pypose.optim.LM, robust modes, degenerate inputs."""

from __future__ import annotations

import copy
import dataclasses
import re

import pytest
import torch

from tactile_slam.config import PoseGraphConfig
from tactile_slam.posegraph import se3
from tactile_slam.posegraph.graph import GraphError, PoseGraph
from tactile_slam.posegraph.reference import solve_pypose
from tactile_slam.posegraph.solver import SolverError, solve
from tactile_slam.posegraph.synthetic import synthetic_scan


def _trans_err_mm(P: torch.Tensor, gt: torch.Tensor) -> float:
    """Mean translation error (mm) after expressing both in the frame of node 0."""
    P = se3.inverse(P[0]) @ P
    return float((P[:, :3, 3] - gt[:, :3, 3]).norm(dim=-1).mean() * 1e3)


def _rot_err_rad(P: torch.Tensor, gt: torch.Tensor) -> float:
    P = se3.inverse(P[0]) @ P
    return float(se3.log(se3.inverse(gt) @ P)[:, 3:].norm(dim=-1).mean())


@pytest.fixture(scope="module")
def scan():
    return synthetic_scan(150, 150, seed=5, radius_m=0.006)


class TestAccuracy:
    def test_recovers_ground_truth_better_than_odometry(self, scan):
        g = copy.deepcopy(scan.graph)
        odo_t, odo_r = _trans_err_mm(g.poses(), scan.gt), _rot_err_rad(g.poses(), scan.gt)
        rep = solve(g)
        assert rep.converged and rep.cost_final < rep.cost_initial
        assert rep.n_variables == 150 and rep.n_factors == g.num_edges + 1
        t, r = _trans_err_mm(g.poses(), scan.gt), _rot_err_rad(g.poses(), scan.gt)
        assert t < 0.5 * odo_t and r < 0.5 * odo_r
        # at the optimum the gradient vanishes: a second solve does not move
        before = g.poses()
        rep2 = solve(g)
        assert rep2.iterations <= 1
        assert torch.allclose(g.poses(), before, atol=1e-9)

    def test_exact_measurements_give_exact_poses(self):
        s = synthetic_scan(80, 60, seed=1, radius_m=0.005, odometry_sigma=(0.0, 0.0),
                           loop_sigma=(0.0, 0.0))
        g = s.graph
        g.set_poses(torch.arange(80), g.poses() @ se3.exp(torch.randn(80, 6, dtype=torch.float64) * 1e-3))
        g.set_poses(torch.tensor([0]), torch.eye(4, dtype=torch.float64)[None])
        solve(g)
        assert torch.allclose(g.poses(), s.gt, atol=1e-9)

    @pytest.mark.parametrize("seed", [0, 1])
    def test_agrees_with_pypose_lm(self, seed):
        s = synthetic_scan(15, 8, seed=seed, radius_m=0.003, coverage_spacing_m=0.0)
        g1, g2 = s.graph, copy.deepcopy(s.graph)
        rep = solve(g1)
        ref = solve_pypose(g2)
        assert rep.cost_final == pytest.approx(ref["cost_final"], rel=1e-6)
        assert torch.allclose(g1.poses(), g2.poses(), atol=1e-8)


class TestStructure:
    def test_one_node(self):
        g = PoseGraph()
        g.add_node(3, se3.exp(torch.tensor([1e-3, 0, 0, 0, 0.2, 0], dtype=torch.float64)))
        g.add_prior(3)
        rep = solve(g)
        assert rep.converged
        assert torch.allclose(g.pose(3), torch.eye(4, dtype=torch.float64), atol=1e-12)

    def test_leaves_ordinary_tensors_and_the_thread_setting(self, scan):
        """The solve runs on one thread under inference mode; afterwards the caller's thread
        count is back, and the poses and weights it leaves can be changed in place, so the
        graph keeps growing and solving outside inference mode."""
        g = copy.deepcopy(scan.graph)
        threads = torch.get_num_threads()
        rep = solve(g)
        assert torch.get_num_threads() == threads
        assert not rep.loop_weights.is_inference() and not g.poses().is_inference()
        rep.loop_weights[0] = 0.5
        g.add_node(10_000, g.pose(149) @ se3.exp(torch.tensor([0, 0, 0, 1e-4, 0, 0], dtype=torch.float64)))
        g.add_between(int(g.ids[-2]), 10_000, se3.exp(torch.tensor([0, 0, 0, 1e-4, 0, 0], dtype=torch.float64)))
        g.set_poses(torch.tensor([0]), g.poses(torch.tensor([0]).tolist()))
        assert solve(g).converged

    def test_empty_graph(self):
        rep = solve(PoseGraph())
        assert rep.n_variables == 0 and rep.iterations == 0

    def test_disconnected_groups_each_with_prior(self):
        s = synthetic_scan(120, 60, n_sessions=3, seed=2, radius_m=0.005)
        g = s.graph
        solve(g)
        for k in range(3):
            ids = torch.nonzero(s.session == k).flatten()
            P = g.poses(ids.tolist())
            gt = se3.inverse(s.gt[ids[0]]) @ s.gt[ids]
            assert torch.allclose(P[0], torch.eye(4, dtype=torch.float64), atol=1e-6)
            assert _trans_err_mm(P, gt) < 0.2

    def test_group_without_prior_raises(self):
        g = PoseGraph()
        g.add_nodes([0, 1, 2, 3], torch.eye(4, dtype=torch.float64).expand(4, 4, 4))
        g.add_prior(0)
        g.add_between(0, 1, torch.eye(4))
        g.add_between(2, 3, torch.eye(4))
        threads = torch.get_num_threads()
        with pytest.raises(SolverError, match="no prior"):
            solve(g)
        # the solver's context is left behind the error too
        assert torch.get_num_threads() == threads and not torch.is_inference_mode_enabled()

    def test_subset_holds_others_fixed(self, scan):
        g = copy.deepcopy(scan.graph)
        before = g.poses()
        rows = torch.arange(50, 100)
        rep = solve(g, rows=rows)
        after = g.poses()
        assert rep.n_variables == 50
        mask = torch.ones(150, dtype=torch.bool)
        mask[rows] = False
        assert torch.equal(after[mask], before[mask])
        assert not torch.allclose(after[rows], before[rows])

    def test_unknown_robust_mode(self, scan):
        with pytest.raises(GraphError, match="robust"):
            solve(copy.deepcopy(scan.graph), PoseGraphConfig(robust="tukey"))

    @pytest.mark.parametrize("rows", [[7], [-1], [1, 4]])
    def test_rows_outside_the_graph_are_refused(self, rows):
        """A row past the end used to raise a bare IndexError, and -1 was taken as the last row."""
        g = _chain(4)
        before = g.poses()
        bad = [r for r in rows if not 0 <= r < 4]
        with pytest.raises(GraphError, match=re.escape(f"rows {bad} are outside the graph's rows 0..3")):
            solve(g, rows=torch.tensor(rows))
        assert torch.equal(g.poses(), before)

    def test_rows_may_be_a_list_or_empty(self):
        g = _chain(4)
        assert solve(g, rows=[]).n_variables == 0
        assert solve(g, rows=[1, 2]).n_variables == 2


def _chain(n: int) -> PoseGraph:
    """``n`` nodes 1 mm apart along x, a prior on node 0, odometry that agrees with them."""
    g = PoseGraph()
    g.add_nodes(range(n), se3.exp(torch.tensor([[1e-3 * k, 0, 0, 0, 0, 0] for k in range(n)], dtype=torch.float64)))
    g.add_prior(0)
    for k in range(n - 1):
        g.add_between(k, k + 1, se3.exp(torch.tensor([1e-3, 0, 0, 0, 0, 0], dtype=torch.float64)))
    return g


class TestConvergence:
    def test_converged_at_the_optimum_of_conflicting_edges(self):
        """Three edges 0 -> 1 of 1, 1 and 2 mm: one step reaches the least-squares optimum (4/3
        mm); the next cannot lower the cost by more than rounding. That used to push lambda past
        its bound and report converged=False."""
        g = _chain(4)
        for x in (1e-3, 2e-3):
            g.add_between(0, 1, se3.exp(torch.tensor([x, 0, 0, 0, 0, 0], dtype=torch.float64)))
        ref = copy.deepcopy(g)
        rep = solve(g)
        assert rep.converged and rep.iterations == 1
        assert g.pose(1)[0, 3].item() == pytest.approx(4e-3 / 3, abs=1e-12)
        assert rep.cost_final == pytest.approx(solve_pypose(ref)["cost_final"], rel=1e-9)
        assert torch.allclose(g.poses(), ref.poses(), atol=1e-12)

    def test_gnc_converged_when_its_last_stage_starts_at_the_optimum(self):
        """GNC's last weighted LM starts where the previous stage ended, at its optimum: all its
        steps are rejected by rounding, which used to report converged=False."""
        s = synthetic_scan(30, 10, seed=0, radius_m=0.005)
        noise = torch.randn(30, 6, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
        s.graph.set_poses(torch.arange(30), s.graph.poses() @ se3.exp(noise * torch.tensor([1e-3] * 3 + [0.05] * 3)))
        rep = solve(s.graph, PoseGraphConfig(robust="gnc"))
        assert rep.converged and not rep.rejected_loops

    def test_stuck_solve_is_not_converged(self):
        """Far from the optimum (rotations perturbed by ~1 rad) with lambda capped at 1e-4, every
        step raises the cost: the solve gives up and says so."""
        s = synthetic_scan(30, 10, seed=4, radius_m=0.005)
        noise = torch.randn(30, 6, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
        s.graph.set_poses(torch.arange(30), s.graph.poses() @ se3.exp(noise * torch.tensor([1e-3] * 3 + [1.0] * 3)))
        g = copy.deepcopy(s.graph)
        stuck = solve(g, PoseGraphConfig(lambda_max=1e-4))
        free = solve(s.graph)
        assert not stuck.converged
        assert free.converged and stuck.cost_final > 2 * free.cost_final


@pytest.fixture(scope="module")
def outlier_scan():
    """A scan with one wrong loop (0.3 rad, 2.2 mm off) added; returns (scan, edge index)."""
    s = synthetic_scan(80, 70, seed=7, radius_m=0.005)
    g = s.graph
    wrong = s.gt[[20]].inverse() @ s.gt[[70]] @ se3.exp(
        torch.tensor([[2e-3, -1e-3, 0.0, 0.0, 0.0, 0.3]], dtype=torch.float64))
    bad = g.add_between(20, 70, wrong[0], kind="loop")
    return s, bad


class TestRobust:
    def test_gnc_rejects_outlier_loop(self, outlier_scan):
        s, bad = outlier_scan
        g_plain, g_gnc = copy.deepcopy(s.graph), copy.deepcopy(s.graph)
        solve(g_plain)
        rep = solve(g_gnc, PoseGraphConfig(robust="gnc"))
        assert bad in rep.rejected_loops
        assert len(rep.rejected_loops) <= 2  # valid loops are (almost) all kept
        assert rep.loop_weights[bad] == 0.0
        assert _trans_err_mm(g_gnc.poses(), s.gt) < 0.5 * _trans_err_mm(g_plain.poses(), s.gt)

    @pytest.mark.parametrize("kernel", ["huber", "cauchy"])
    def test_kernels_downweight_outlier(self, outlier_scan, kernel):
        s, bad = outlier_scan
        g_plain, g_rob = copy.deepcopy(s.graph), copy.deepcopy(s.graph)
        solve(g_plain)
        rep = solve(g_rob, PoseGraphConfig(robust=kernel))
        assert rep.loop_weights[bad] < 0.2
        assert _trans_err_mm(g_rob.poses(), s.gt) < _trans_err_mm(g_plain.poses(), s.gt)

    def test_odometry_never_downweighted(self, outlier_scan):
        s, _ = outlier_scan
        rep = solve(copy.deepcopy(s.graph), dataclasses.replace(PoseGraphConfig(), robust="cauchy"))
        assert (rep.loop_weights[~s.graph.edges.loop] == 1.0).all()
