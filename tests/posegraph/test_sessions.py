"""Union-find of sessions, merge rules and re-initialisation through the loop measurement."""

from __future__ import annotations

import pytest
import torch

from tactile_slam.posegraph import se3
from tactile_slam.posegraph.graph import PoseGraph
from tactile_slam.posegraph.sessions import SessionError, SessionGroups
from tactile_slam.posegraph.solver import solve
from tactile_slam.posegraph.synthetic import synthetic_scan


def _build(scan) -> tuple[PoseGraph, SessionGroups]:
    groups = SessionGroups()
    for k, s in enumerate(scan.session.tolist()):
        groups.add_keyframe(k, s)
    return scan.graph, groups


class TestUnionFind:
    def test_smoke(self):
        sg = SessionGroups()
        assert sg.add_keyframe(0, 0) and not sg.add_keyframe(1, 0) and sg.add_keyframe(2, 5)
        assert sg.groups == [0, 5] and sg.num_sessions == 2
        assert sg.size(0) == 2 and sg.size(5) == 1
        assert sg.group_of(1) == 0 and sg.anchor(5) == 2 and sg.members(0) == [0, 1]

    def test_errors(self):
        sg = SessionGroups()
        sg.add_keyframe(0, 0)
        with pytest.raises(SessionError, match="already"):
            sg.add_keyframe(0, 1)
        with pytest.raises(SessionError, match="unknown keyframe 9"):
            sg.group_of(9)
        with pytest.raises(SessionError, match="unknown session 4"):
            sg.find(4)

    def test_no_merge_within_one_group(self):
        g = PoseGraph()
        g.add_nodes([0, 1], torch.eye(4, dtype=torch.float64).expand(2, 4, 4))
        g.add_prior(0)
        sg = SessionGroups()
        sg.add_keyframe(0, 0)
        sg.add_keyframe(1, 0)
        res = sg.merge(g, 1, [(0, torch.eye(4))])
        assert res.absorbed == [] and res.root == 0 and g.has_prior(0)


class TestMerge:
    @pytest.fixture()
    def two_sessions(self):
        return synthetic_scan(100, 80, n_sessions=2, seed=11, radius_m=0.005)

    def _first_cross_loop(self, scan, t_session: int):
        for (r, t), Z in zip(scan.loops.tolist(), scan.loop_Z):
            if scan.session[r] != scan.session[t] and scan.session[t] == t_session:
                return r, t, Z
        pytest.skip("no cross-session loop in this scan")

    def test_merge_reinitialises_and_solves_to_ground_truth(self, two_sessions):
        s = two_sessions
        g, sg = _build(s)
        r, t, Z = self._first_cross_loop(s, 1)
        res = sg.merge(g, t, [(r, Z)])
        # tie-breaking: equal sizes (50/50) go to t's group, so session 0 (r's) is absorbed
        assert res.root == 1 and res.absorbed == [0]
        assert res.removed_priors == [0] and not g.has_prior(0) and g.has_prior(50)
        assert sorted(res.moved) == list(range(50))
        assert sg.groups == [1] and sg.size(1) == 100
        # the loop holds exactly after re-initialisation
        assert torch.allclose(se3.inverse(g.pose(r)) @ g.pose(t), Z, atol=1e-12)
        g.add_between(r, t, Z, kind="loop")
        for (a, b), Zab in zip(s.loops.tolist(), s.loop_Z):
            if s.session[a] != s.session[b] and (a, b) != (r, t):
                g.add_between(a, b, Zab, kind="loop")
        solve(g)
        P = g.poses()
        gt = se3.inverse(s.gt[50]) @ s.gt  # start = head of the root session
        assert torch.allclose(P[50], torch.eye(4, dtype=torch.float64), atol=1e-6)
        assert float((P[:, :3, 3] - gt[:, :3, 3]).norm(dim=-1).max()) < 2e-4

    def test_larger_group_is_root(self):
        s = synthetic_scan(90, 60, n_sessions=3, seed=12, radius_m=0.005)
        g, sg = _build(s)
        sg.merge(g, 45, [(5, s.gt[5].inverse() @ s.gt[45])])  # groups 0 + 1 -> 60 keyframes
        big = sg.group_of(0)
        assert sg.size(big) == 60
        Z = s.gt[30].inverse() @ s.gt[75]
        res = sg.merge(g, 75, [(30, Z)])  # group of session 2 (30 kf) joins the 60-kf group
        assert res.root == big and res.absorbed == [2] and sorted(res.moved) == list(range(60, 90))
        assert torch.allclose(se3.inverse(g.pose(30)) @ g.pose(75), Z, atol=1e-12)
        assert g.priors.rows.numel() == 1

    def test_three_groups_in_one_step(self):
        s = synthetic_scan(90, 60, n_sessions=3, seed=13, radius_m=0.005)
        g, sg = _build(s)
        Z1 = s.gt[10].inverse() @ s.gt[80]
        Z2 = s.gt[40].inverse() @ s.gt[80]
        res = sg.merge(g, 80, [(10, Z1), (40, Z2), (11, s.gt[11].inverse() @ s.gt[80])])
        assert res.root == 2 and res.absorbed == [0, 1]  # all 30: the tie goes to t's group
        assert sg.groups == [2] and g.priors.rows.tolist() == [60]
        assert torch.allclose(se3.inverse(g.pose(10)) @ g.pose(80), Z1, atol=1e-12)
        assert torch.allclose(se3.inverse(g.pose(40)) @ g.pose(80), Z2, atol=1e-12)

    def test_without_reinit_poses_stay(self, two_sessions):
        s = two_sessions
        g, sg = _build(s)
        before = g.poses()
        r, t, Z = self._first_cross_loop(s, 1)
        res = sg.merge(g, t, [(r, Z)], reinit=False)
        assert res.moved == [] and torch.equal(g.poses(), before)
