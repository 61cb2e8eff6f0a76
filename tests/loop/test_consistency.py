"""Back-end loop acceptance: loops against the map estimate, merges only on agreeing loops."""

from __future__ import annotations

import math
from dataclasses import replace

import pytest
import torch

from tactile_slam.backend import BackEnd
from tactile_slam.config import Config
from tactile_slam.loop.consistency import (DriftModel, LoopGate, MotionGraph, Selection, closing_prediction,
                                          consistent,                                           motion_mm)
from tactile_slam.loop.detector import Loop
from tactile_slam.posegraph import se3
from tactile_slam.posegraph.graph import PoseGraph
from tactile_slam.posegraph.sessions import SessionGroups
from tactile_slam.posegraph.solver import solve
from tactile_slam.registration.result import pose_error
from tactile_slam.tracking.keyframe import Keyframe
from tests.registration.surfaces import Surface, frames

MODEL = DriftModel(base_rot_deg=3.0, base_trans_mm=0.5, rot_deg_per_mm=0.1, trans_mm_per_mm=0.02, lever_mm=12.7)


def pose(rot_axis: tuple[float, float, float], angle_deg: float, t_mm: tuple[float, float, float]) -> torch.Tensor:
    """``(4, 4)`` float64 rigid transform, translation in mm (stored in metres)."""
    axis = torch.tensor(rot_axis, dtype=torch.float64)
    xi = torch.cat([torch.tensor(t_mm, dtype=torch.float64) * 1e-3, axis / axis.norm() * math.radians(angle_deg)])
    T = se3.exp(xi)
    T[:3, 3] = torch.tensor(t_mm, dtype=torch.float64) * 1e-3
    return T


def arc(n: int, step_mm: float = 1.0, turn_deg: float = 2.0) -> torch.Tensor:
    """True ``start_T_kf`` ``(n, 4, 4)`` of a sensor sliding along a gentle arc."""
    step = pose((0, 0, 1), turn_deg, (step_mm, 0.0, 0.0))
    out = [torch.eye(4, dtype=torch.float64)]
    for _ in range(n - 1):
        out.append(out[-1] @ step)
    return torch.stack(out)


def drifted(true: torch.Tensor, scale: float = 1.03, rot_bias_deg: float = 0.1) -> tuple[torch.Tensor, list]:
    """Odometry with a scale error and a rotation bias per step, and its chained estimate."""
    bias = pose((1, 1, 0), rot_bias_deg, (0, 0, 0))
    odo = []
    for k in range(1, len(true)):
        Z = se3.inverse(true[k - 1]) @ true[k]
        Z[:3, 3] *= scale
        odo.append(Z @ bias)
    est = [true[0]]
    for Z in odo:
        est.append(est[-1] @ Z)
    return torch.stack(est), odo


def loop(r: int, t: int, r_T_t: torch.Tensor) -> Loop:
    return Loop(r, t, r_T_t, 0.99, 0.9, 20, torch.eye(4, dtype=torch.float64))


# the shell's symmetry: a half turn about the object's y axis, here through x = 4.5 mm
SYMMETRY = pose((0, 0, 1), 0.0, (4.5, 0.0, 0.0)) @ pose((0, 1, 0), 180.0, (0.0, 0.0, 0.0)) @ \
    pose((0, 0, 1), 0.0, (-4.5, 0.0, 0.0))


def symmetric_false(true: torch.Tensor, r: int, t: int) -> torch.Tensor:
    """The measurement ``r_T_t`` of a false loop on a half-turn-symmetric texture: touch ``t``
    looks exactly like a touch at the symmetric place, so the measurement is the relative
    pose of that place (the true relative pose composed with a half turn)."""
    return se3.inverse(true[r]) @ SYMMETRY @ true[t]


# ------------------------------------------------------------------ pure functions


def test_motion_counts_translation_and_lever_rotation():
    assert float(motion_mm(pose((0, 0, 1), 0.0, (3.0, 4.0, 0.0)), 10.0)) == pytest.approx(5.0)
    assert float(motion_mm(pose((0, 0, 1), 90.0, (0.0, 0.0, 0.0)), 10.0)) == pytest.approx(10 * math.pi / 2)


def test_discrepancy_and_tolerance_grow_with_path():
    a = pose((0, 0, 1), 10.0, (1.0, 2.0, 0.0))
    b = a @ pose((0, 0, 1), 4.0, (0.0, 0.0, 0.0))
    b[:3, 3] += torch.tensor([1.0e-3, 0.0, 0.0], dtype=torch.float64)
    rot, trans = pose_error(a[None], b[None])
    assert float(rot) == pytest.approx(4.0) and float(trans) == pytest.approx(1.0)
    # 4 deg / 1 mm off: beyond the base tolerance (3 deg, 0.5 mm), within it after 25 mm of
    # path; an unknown (infinite) path never passes
    ok = consistent(a.expand(3, 4, 4), b.expand(3, 4, 4), torch.tensor([0.0, 25.0, math.inf]), MODEL)
    assert ok.tolist() == [False, True, False]
    assert MODEL.tolerance(25.0) == pytest.approx((5.5, 1.0))


def test_motion_graph_shortest_paths_are_bounded_and_local():
    g = MotionGraph(lever_mm=10.0)
    step = pose((0, 0, 1), 0.0, (1.0, 0.0, 0.0))
    for k in range(9):
        g.add_edge(k, k + 1, step)
    g.add_edge(0, 9, pose((0, 0, 1), 0.0, (2.0, 0.0, 0.0)))  # a loop closes the chain
    g.add_node(20)
    d = g.paths(0, [5, 8, 20])
    assert d[5] == pytest.approx(5.0) and d[8] == pytest.approx(3.0) and d[20] == math.inf
    assert g.paths(0, [5], limit=4.0)[5] == math.inf


# ------------------------------------------------------------------ within one group


def test_doubtful_loops_within_a_group_need_agreement():
    """Beyond the tolerance but within doubt_factor x it (a tracker that slipped, or a
    periodic false match): held until a second loop from distinct keyframes agrees."""
    true = arc(30)
    est, odo = drifted(true, scale=1.0, rot_bias_deg=0.0)
    slip = pose((0, 0, 1), 6.0, (0.0, 0.0, 0.0))  # the estimate of 25..29 turned by 6 deg
    est[25:] = est[24] @ slip @ se3.inverse(est[24]) @ est[25:]
    gate = LoopGate(MODEL)
    for k, Z in enumerate(odo):
        gate.add_factor(k, k + 1, Z)
    first = loop(20, 26, se3.inverse(true[20]) @ true[26])
    assert gate.select([first], lambda k: 0, lambda k: est[k]).accepted == []
    assert gate.stats.doubtful == 1 and len(gate.pending) == 1 and gate.held() == [(first, "doubtful")]
    second = loop(21, 28, se3.inverse(true[21]) @ true[28])
    sel = gate.select([second], lambda k: 0, lambda k: est[k])
    assert sel.accepted == [first, second] and sel.merges == [] and gate.pending == [] and gate.held() == []


def test_symmetric_false_loop_rejected_true_loop_with_drift_accepted():
    true = arc(30)
    est, odo = drifted(true)
    gate = LoopGate(MODEL)
    gate.add_node(0)
    for k, Z in enumerate(odo):
        gate.add_factor(k, k + 1, Z)
    t = 29
    true_loop = loop(0, t, se3.inverse(true[0]) @ true[t])
    false_loop = loop(4, t, symmetric_false(true, 4, t))
    # the drifted estimate really is off: a fixed tolerance of the base alone would reject the true loop
    rot, trans = pose_error((se3.inverse(est[0]) @ est[t])[None], true_loop.ref_T_tar[None])
    assert float(rot) > 1.0 and float(trans) > MODEL.base_trans_mm
    sel = gate.select([true_loop, false_loop], lambda k: 0, lambda k: est[k])
    assert sel.accepted == [true_loop] and sel.merges == []
    assert gate.stats.rejected_consistency == 1 and gate.held() == [(false_loop, "inconsistent")]


def test_repetitive_loop_within_a_group_gets_no_drift_allowance():
    """On a texture that matches itself, a false loop one period off agrees with an
    estimate that has drifted as well as the true loop does. So a repetitive loop counts
    only within the loop's own error (the base tolerance): the true loop of the drifted
    arc, accepted when its texture is unique, is dropped as repetitive; a short repetitive
    loop that the estimate predicts closely is accepted."""
    true = arc(30)
    est, odo = drifted(true)

    def gate_with_odometry():
        gate = LoopGate(MODEL)
        gate.add_node(0)
        for k, Z in enumerate(odo):
            gate.add_factor(k, k + 1, Z)
        return gate

    far = se3.inverse(true[0]) @ true[29]
    rot, trans = pose_error((se3.inverse(est[0]) @ est[29])[None], far[None])
    assert float(rot) > 1.0 and float(trans) > MODEL.base_trans_mm  # beyond the base, within the drift
    unique = loop(0, 29, far)
    assert gate_with_odometry().select([unique], lambda k: 0, lambda k: est[k]).accepted == [unique]
    repeated = replace(loop(0, 29, far), repetitive=True)
    gate = gate_with_odometry()
    sel = gate.select([repeated], lambda k: 0, lambda k: est[k])
    assert sel.accepted == [] and gate.pending == [] and gate.held() == [(repeated, "repetitive")]
    assert gate.stats.repetitive == 1 and gate.stats.doubtful == 0
    near = replace(loop(26, 28, se3.inverse(true[26]) @ true[28]), repetitive=True)
    assert gate.select([near], lambda k: 0, lambda k: est[k]).accepted == [near]
    trusting = LoopGate(MODEL, trust_repetitive=True)
    for k, Z in enumerate(odo):
        trusting.add_factor(k, k + 1, Z)
    assert trusting.select([repeated], lambda k: 0, lambda k: est[k]).accepted == [repeated]


def test_beyond_a_half_turn_of_drift_nothing_is_rejected():
    """When the doubt band exceeds 180 degrees the estimate cannot refute a loop: it waits for
    agreement instead of being rejected, and the drift search stops there."""
    loose = DriftModel(base_rot_deg=3.0, base_trans_mm=0.5, rot_deg_per_mm=10.0, trans_mm_per_mm=0.02, lever_mm=12.7)
    assert loose.scaled(5.0).half_turn_path_mm() == pytest.approx((180 - 15) / 50)
    true = arc(8)
    gate = LoopGate(loose)
    for k in range(7):
        gate.add_factor(k, k + 1, se3.inverse(true[k]) @ true[k + 1])
    sel = gate.select([loop(0, 7, symmetric_false(true, 0, 7))], lambda k: 0, lambda k: true[k])
    assert sel.accepted == [] and gate.stats.rejected_consistency == 0 and gate.stats.doubtful == 1


def test_recent_loop_shortens_the_drift_path():
    true = arc(60, turn_deg=6.0)  # a full circle: keyframe 58 is back next to keyframe 0
    _, odo = drifted(true)
    gate = LoopGate(MODEL)
    for k, Z in enumerate(odo):
        gate.add_factor(k, k + 1, Z)
    far = gate.motion.paths(59, [0])[0]
    gate.add_factor(0, 58, se3.inverse(true[0]) @ true[58])  # an accepted loop near the query
    near = gate.motion.paths(59, [0])[0]
    assert near < 0.1 * far


# ------------------------------------------------------------------ across groups


def chained_sessions(true: torch.Tensor, per: int) -> tuple[PoseGraph, SessionGroups, list]:
    """The keyframes ``true`` ``(K, 4, 4)`` in sessions of ``per``, each session in its own
    frame with exact odometry: ``(graph, groups, odometry factors (i, j, i_T_j))``."""
    graph, groups, factors = PoseGraph(), SessionGroups(), []
    for k in range(len(true)):
        if groups.add_keyframe(k, k // per):
            graph.add_node(k)
            graph.add_prior(k)
        else:
            Z = se3.inverse(true[k - 1]) @ true[k]
            graph.add_node(k, graph.pose(k - 1) @ Z)
            graph.add_between(k - 1, k, Z)
            factors.append((k - 1, k, Z))
    return graph, groups, factors


@pytest.fixture()
def two_sessions():
    """Session 0 (keyframes 0-14) and session 1 (15-29) on one arc, each in its own frame."""
    true = arc(30)
    graph, groups, factors = chained_sessions(true, 15)
    gate = LoopGate(MODEL)
    for k in range(30):
        gate.add_node(k)
    for i, j, Z in factors:
        gate.add_factor(i, j, Z)
    return true, graph, groups, gate


def _apply(sel, graph, groups, gate):
    for lp in sel.accepted:
        graph.add_between(lp.ref_id, lp.tar_id, lp.ref_T_tar, kind="loop")
        gate.add_factor(lp.ref_id, lp.tar_id, lp.ref_T_tar)
    for t, r, Z in sel.merges:
        groups.merge(graph, t, [(r, Z)])


def test_single_inter_group_loop_is_not_merged(two_sessions):
    true, graph, groups, gate = two_sessions
    false_loop = loop(3, 16, symmetric_false(true, 3, 16))
    sel = gate.select([false_loop], groups.group_of, graph.pose)
    assert sel.accepted == [] and sel.merges == [] and len(gate.pending) == 1
    # a second false loop from the *same* query keyframe is no independent evidence
    second = loop(5, 16, symmetric_false(true, 5, 16))
    sel = gate.select([second], groups.group_of, graph.pose)
    assert sel.merges == [] and groups.group_of(16) != groups.group_of(3)
    assert gate.held() == [(false_loop, "waiting"), (second, "waiting")]


def test_held_loops_between_groups_say_why_they_were_dropped(two_sessions):
    true, graph, groups, gate = two_sessions
    rep = replace(loop(12, 17, se3.inverse(true[12]) @ true[17]), repetitive=True)
    amb = replace(loop(10, 19, se3.inverse(true[10]) @ true[19]), ambiguous=True)
    both = replace(loop(11, 21, se3.inverse(true[11]) @ true[21]), repetitive=True, ambiguous=True)
    sel = gate.select([rep, amb, both], groups.group_of, graph.pose)
    assert sel.accepted == [] and gate.pending == [] and gate.stats.repetitive == 3
    assert gate.held() == [(rep, "repetitive"), (amb, "ambiguous"), (both, "repetitive")]


@pytest.mark.parametrize("distinct, merges", [("queries", True), ("both", False)])
def test_two_queries_matching_one_coverage_keyframe(two_sessions, distinct, merges):
    """After contact loss the coverage set often keeps one keyframe of the old region: two
    separate detections (queries 17 and 19) agreeing through that one keyframe are
    independent support under "queries", not under "both"."""
    true, graph, groups, _ = two_sessions
    gate = LoopGate(MODEL, distinct=distinct)
    for k in range(29):
        if groups.group_of(k) == groups.group_of(k + 1):
            gate.add_factor(k, k + 1, se3.inverse(true[k]) @ true[k + 1])
    gate.select([loop(12, 17, se3.inverse(true[12]) @ true[17])], groups.group_of, graph.pose)
    sel = gate.select([loop(12, 19, se3.inverse(true[12]) @ true[19])], groups.group_of, graph.pose)
    assert bool(sel.merges) == merges and len(sel.accepted) == (2 if merges else 0)
    if merges:
        _apply(sel, graph, groups, gate)
        solve(graph)
        est = graph.poses()
        rot, trans = pose_error(se3.inverse(est[0]) @ est, true)
        assert groups.group_of(29) == groups.group_of(0)
        assert float(rot.max()) < 1e-6 and float(trans.max()) < 1e-6


def test_two_agreeing_inter_group_loops_merge_with_correct_poses(two_sessions):
    true, graph, groups, gate = two_sessions
    false_loop = loop(3, 17, symmetric_false(true, 3, 17))
    first = loop(12, 17, se3.inverse(true[12]) @ true[17])
    sel = gate.select([first, false_loop], groups.group_of, graph.pose)
    assert sel.merges == []
    second = loop(10, 19, se3.inverse(true[10]) @ true[19])
    sel = gate.select([second], groups.group_of, graph.pose)
    assert {(lp.ref_id, lp.tar_id) for lp in sel.accepted} == {(12, 17), (10, 19)}
    assert len(sel.merges) == 1 and [(p.a_id, p.b_id) for p in gate.pending] == [(3, 17)]
    _apply(sel, graph, groups, gate)
    assert groups.group_of(29) == groups.group_of(0)
    solve(graph)
    # the false loop left out of the merge meets the merged estimate at the next keyframe
    assert gate.select([], groups.group_of, graph.pose).accepted == [] and gate.pending == []
    assert gate.stats.rejected_consistency == 1
    est = graph.poses()
    rot, trans = pose_error(se3.inverse(est[0]) @ est, true)  # true: start = keyframe 0
    assert float(rot.max()) < 1e-6 and float(trans.max()) < 1e-6


def test_disagreeing_supported_sets_do_not_merge(two_sessions):
    """Both faces of a symmetric object seen: two agreeing true and two agreeing false loops."""
    true, graph, groups, gate = two_sessions
    loops17 = [loop(12, 17, se3.inverse(true[12]) @ true[17]),
               loop(2, 17, symmetric_false(true, 2, 17))]
    loops19 = [loop(10, 19, se3.inverse(true[10]) @ true[19]),
               loop(4, 19, symmetric_false(true, 4, 19))]
    gate.select(loops17, groups.group_of, graph.pose)
    sel = gate.select(loops19, groups.group_of, graph.pose)
    assert sel.merges == [] and sel.accepted == [] and gate.stats.ambiguous == 1 and len(gate.pending) == 4


def test_pending_loops_are_checked_once_their_groups_join(two_sessions):
    true, graph, groups, gate = two_sessions
    late = loop(1, 28, se3.inverse(true[1]) @ true[28])
    late_false = loop(6, 27, symmetric_false(true, 6, 27))
    gate.select([late_false], groups.group_of, graph.pose)
    gate.select([late], groups.group_of, graph.pose)
    # other loops merge the groups, then the pending loops are swept
    joint = loop(12, 17, se3.inverse(true[12]) @ true[17])
    _apply(Selection([joint], [(17, 12, joint.ref_T_tar)]), graph, groups, gate)
    sel = gate.select([], groups.group_of, graph.pose)
    assert sel.accepted == [late] and gate.pending == [] and gate.stats.rejected_consistency == 1


def test_closing_prediction_of_every_combination():
    """Three groups with their own start frames: loops measured from the true poses close the
    cycle exactly, in every combination of one loop per leg; a half turn on one does not."""
    true = arc(45)
    starts = [true[0], true[15], true[30]]  # group start frames
    local = lambda k: se3.inverse(starts[k // 15]) @ true[k]  # noqa: E731
    implied = lambda x, T, y: local(x) @ T @ se3.inverse(local(y))  # noqa: E731
    rel = lambda r, t: se3.inverse(true[r]) @ true[t]  # noqa: E731
    A_T_B = torch.stack([implied(12, rel(12, 17), 17), implied(3, rel(3, 20), 20)])
    B_T_C = torch.stack([implied(27, rel(27, 32), 32), implied(16, symmetric_false(true, 16, 40), 40),
                         implied(29, rel(29, 31), 31)])
    x, y = [35, 40], [5, 9]  # loops C -> A
    pred = closing_prediction(A_T_B, B_T_C, torch.stack([local(k) for k in x]), torch.stack([local(k) for k in y]))
    assert pred.shape == (2, 3, 2, 4, 4)
    meas = torch.stack([rel(a, b) for a, b in zip(x, y)])
    for j in (0, 2):
        assert torch.allclose(pred[:, j], meas.expand(2, 2, 4, 4), atol=1e-12)
    rot, _ = pose_error(pred[:, 1].reshape(-1, 4, 4), meas.repeat(2, 1, 1))
    assert torch.allclose(rot, torch.full_like(rot, 180.0), atol=1e-6)


@pytest.fixture()
def three_sessions():
    """Sessions 0 (keyframes 0-14), 1 (15-29) and 2 (30-44) on one arc, each in its own frame."""
    true = arc(45)
    return (true, *chained_sessions(true, 15))


def _gate(factors, **kw) -> LoopGate:
    gate = LoopGate(MODEL, **kw)
    for i, j, Z in factors:
        gate.add_factor(i, j, Z)
    return gate


def test_three_single_loops_closing_a_cycle_merge_three_groups(three_sessions):
    """Short sessions seldom give two loops to one group; one loop between each pair of
    three groups, from distinct queries, that composes to the identity merges all three."""
    true, graph, groups, factors = three_sessions
    gate = _gate(factors)
    rel = lambda r, t: se3.inverse(true[r]) @ true[t]  # noqa: E731
    a_b, b_c, c_a = loop(12, 17, rel(12, 17)), loop(27, 32, rel(27, 32)), loop(5, 35, rel(5, 35))
    assert gate.select([a_b], groups.group_of, graph.pose).merges == []
    assert gate.select([b_c], groups.group_of, graph.pose).merges == []
    sel = gate.select([c_a], groups.group_of, graph.pose)
    assert {(lp.ref_id, lp.tar_id) for lp in sel.accepted} == {(12, 17), (27, 32), (5, 35)}
    assert len(sel.merges) == 2 and gate.pending == [] and gate.stats.cycles == 1
    _apply(sel, graph, groups, gate)
    assert len({groups.group_of(k) for k in range(45)}) == 1
    solve(graph)
    est = graph.poses()
    rot, trans = pose_error(se3.inverse(est[0]) @ est, true)
    assert float(rot.max()) < 1e-6 and float(trans.max()) < 1e-6


@pytest.mark.parametrize("min_pairs, merges", [(2, True), (3, False)])
def test_cycle_support_counts_distinct_queries(three_sessions, min_pairs, merges):
    """Query 35 finds both older groups: with query 17's loop that is two detections, enough
    for min_pairs 2 (as two loops between two groups would be), not for 3."""
    true, graph, groups, factors = three_sessions
    gate = _gate(factors, min_pairs=min_pairs)
    rel = lambda r, t: se3.inverse(true[r]) @ true[t]  # noqa: E731
    gate.select([loop(12, 17, rel(12, 17))], groups.group_of, graph.pose)
    sel = gate.select([loop(5, 35, rel(5, 35)), loop(24, 35, rel(24, 35))], groups.group_of, graph.pose)
    assert bool(sel.merges) == merges and len(sel.accepted) == (3 if merges else 0)
    assert gate.stats.cycles == int(merges)


def test_cycle_with_a_false_loop_or_switched_off_does_not_merge(three_sessions):
    true, graph, groups, factors = three_sessions
    rel = lambda r, t: se3.inverse(true[r]) @ true[t]  # noqa: E731
    for false_leg, cycles in ((True, True), (False, False)):
        gate = _gate(factors, cycles=cycles)
        b_c = loop(27, 32, symmetric_false(true, 27, 32) if false_leg else rel(27, 32))
        for t, lp in ((17, loop(12, 17, rel(12, 17))), (32, b_c), (35, loop(5, 35, rel(5, 35)))):
            assert gate.select([lp], groups.group_of, graph.pose).merges == []
        assert len(gate.pending) == 3 and gate.stats.cycles == 0


def test_contradicted_cycle_does_not_merge(three_sessions):
    """A closed cycle, but another waiting loop between two of its groups (a half turn of a
    symmetric object, from a distinct query) contradicts it: nothing merges."""
    true, graph, groups, factors = three_sessions
    gate = _gate(factors)
    rel = lambda r, t: se3.inverse(true[r]) @ true[t]  # noqa: E731
    gate.select([loop(12, 17, rel(12, 17))], groups.group_of, graph.pose)
    gate.select([loop(3, 19, symmetric_false(true, 3, 19))], groups.group_of, graph.pose)
    gate.select([loop(27, 32, rel(27, 32))], groups.group_of, graph.pose)
    sel = gate.select([loop(5, 35, rel(5, 35))], groups.group_of, graph.pose)
    assert sel.merges == [] and sel.accepted == [] and len(gate.pending) == 4
    assert gate.stats.cycles == 0 and gate.stats.ambiguous >= 1


def test_backend_config_defaults_build_a_gate():
    be = BackEnd(Config(), loop_mode=None)
    assert be.gate is not None and be.gate.model.lever_mm == pytest.approx(0.5 * math.hypot(320, 240) * 0.0634)
    assert be.gate.cycles is True and be.gate.trust_repetitive is False
    cfg = replace(Config(), loop=replace(Config().loop, merge_cycles=False, trust_repetitive=True))
    gate = BackEnd(cfg, loop_mode=None).gate
    assert gate.cycles is False and gate.trust_repetitive is True


@pytest.mark.parametrize("trust", [False, True])
def test_backend_does_not_merge_sessions_on_one_repetitive_texture_loop(trust):
    """The detector's periodic-texture trap (two identical touches 12 periods apart) in two
    sessions: the pair verifies across groups and is flagged repetitive (the texture matches
    itself shifted); the back end drops it, or with ``trust_repetitive`` holds it, and never
    merges."""
    surf = Surface(depth=0.6e-3, waves=[(25e-6, 1.0e-3, 0.0, 0.3), (25e-6, 1.0e-3, math.pi / 2, 1.1)])
    fr = frames(surf, [torch.eye(4, dtype=torch.float64)])
    be = BackEnd(replace(Config(), loop=replace(Config().loop, trust_repetitive=trust)))
    for k in range(2):
        be.add(Keyframe(k, k, fr[0], True, torch.eye(4, dtype=torch.float64)))
    assert be.detector.stats.loops == 1  # verified: a local test cannot reject it
    assert be.detector.is_repetitive(be.keyframes[0]) and be.detector.is_repetitive(be.keyframes[1])
    assert be.loops == [] and be.stats.merges == 0 and be.group[0] != be.group[1]
    gate = be.summary()["loop_gate"]
    assert len(be.gate.pending) == gate["pending"] == int(trust) and gate["repetitive"] == int(not trust)
    (held,) = be.held_loops()
    assert (held["ref_id"], held["tar_id"], held["repetitive"]) == (0, 1, True)
    assert held["reason"] == ("waiting" if trust else "repetitive")


def test_bad_gate_settings_are_refused():
    for bad in (dict(base_rot_deg=-1.0), dict(trans_mm_per_mm=float("nan")), dict(lever_mm=float("inf"))):
        kw = dict(base_rot_deg=3.0, base_trans_mm=0.5, rot_deg_per_mm=0.1, trans_mm_per_mm=0.02, lever_mm=12.7) | bad
        with pytest.raises(ValueError, match="drift tolerances"):
            DriftModel(**kw)
    with pytest.raises(ValueError, match="min_pairs"):
        LoopGate(MODEL, min_pairs=0)
    with pytest.raises(ValueError, match="doubt_factor"):
        LoopGate(MODEL, doubt_factor=0.5)
    with pytest.raises(ValueError, match="distinct"):
        LoopGate(MODEL, distinct="one")
    with pytest.raises(ValueError, match="distinct"):
        BackEnd(replace(Config(), loop=replace(Config().loop, merge_distinct="")))
    cfg = Config()
    with pytest.raises(ValueError, match="drift tolerances"):
        BackEnd(replace(cfg, loop=replace(cfg.loop, drift_base_trans_mm=-0.1)))
