"""Alternative starts (tactile_slam/loop/ambiguity.py), the back end holding loops
between groups whose pair also verifies elsewhere (loop.check_ambiguity), and loops moving
to the best nearby alignment (loop.best_nearby)."""

from __future__ import annotations

import math
from dataclasses import replace

import pytest
import torch

from tactile_slam.backend import BackEnd
from tactile_slam.config import Config
from tactile_slam.loop.ambiguity import NEAR, best, elsewhere, starts
from tactile_slam.loop.consistency import DriftModel
from tactile_slam.loop.detector import Loop, LoopDetector
from tactile_slam.posegraph import se3
from tactile_slam.registration.result import pose_error
from tactile_slam.tracking.keyframe import Keyframe
from tests.loop.test_probe import _sessions
from tests.registration.surfaces import frames, rigid, speckled, textured

EYE = torch.eye(4, dtype=torch.float64)
MODEL = DriftModel(base_rot_deg=3.0, base_trans_mm=0.5, rot_deg_per_mm=0.1, trans_mm_per_mm=0.02, lever_mm=12.7)


def test_starts_are_the_prediction_its_shifts_and_turns_about_the_centre():
    q_T_c = rigid(rx_deg=2.0, rz_deg=10.0, tx_mm=0.4, ty_mm=-0.3)
    centre = torch.tensor([0.5e-3, -0.2e-3, -0.4e-3], dtype=torch.float64)
    out = starts(q_T_c, centre, 2.0e-3, 0.5e-3)
    assert out.shape == (12, 4, 4) and out.dtype == torch.float64
    torch.testing.assert_close(out[0], q_T_c)
    moves = out @ se3.inverse(q_T_c)  # what was applied on top of the prediction
    axes = torch.tensor([[1.0, 0, 0], [-1.0, 0, 0], [0, 1.0, 0], [0, -1.0, 0]], dtype=torch.float64)
    for shifts, size in ((slice(1, 5), 1e-3), (NEAR, 0.5e-3)):  # half the radius; the near shift
        torch.testing.assert_close(moves[shifts, :3, :3], EYE[:3, :3].expand(4, 3, 3))
        torch.testing.assert_close(moves[shifts, :3, 3], axes * size)
    for k, deg in zip(range(5, 8), (90.0, 180.0, 270.0)):
        angle = math.degrees(math.atan2(float(moves[k, 1, 0]), float(moves[k, 0, 0]))) % 360.0
        assert angle == pytest.approx(deg)
        torch.testing.assert_close(moves[k, :3, :3] @ centre + moves[k, :3, 3], centre)  # the centre stays
    torch.testing.assert_close(starts(q_T_c, centre, 2.0e-3), out[:8])  # without near starts


def test_starts_refuses_bad_input():
    with pytest.raises(ValueError, match="pose"):
        starts(EYE[:3], torch.zeros(3, dtype=torch.float64), 1e-3, 0.5e-3)
    for bad in (0.0, -1e-3, math.nan):
        with pytest.raises(ValueError, match="radius"):
            starts(EYE, torch.zeros(3, dtype=torch.float64), bad, 0.5e-3)
        with pytest.raises(ValueError, match="near shift"):
            starts(EYE, torch.zeros(3, dtype=torch.float64), 1e-3, bad)


def test_best_takes_the_highest_verified_ccs_among_the_first_and_near_starts():
    ccs = torch.full((4, 12), 0.9, dtype=torch.float64)
    ok = torch.ones(4, 12, dtype=torch.bool)
    ccs[0, 9] = 0.99  # a near start scores higher: taken
    ccs[1, 5] = 0.99  # a far start scores higher: not a near alignment, left to elsewhere()
    ccs[2, 10], ok[2, 10] = 0.99, False  # higher but failed its checks
    ok[3, 0], ccs[3, 11] = False, 0.95  # the first start failed, a near one verified
    assert best(ok, ccs).tolist() == [9, 0, 0, 11]
    assert best(torch.zeros(2, 12, dtype=torch.bool), ccs[:2]).tolist() == [0, 0]  # nothing verified
    nan = ccs[1:2].clone()  # all equal but a far start: the first
    nan[0, 8] = math.nan
    assert best(ok[:1], nan).tolist() == [0]
    with pytest.raises(ValueError, match="S > 11"):
        best(ok[:, :8], ccs[:, :8])


def test_elsewhere_needs_an_alternative_verified_beyond_the_base_tolerance():
    first = rigid(rz_deg=10.0, tx_mm=1.0)
    near = rigid(rz_deg=11.0, tx_mm=1.2)  # 1 deg, 0.2 mm: the same alignment
    far = rigid(rz_deg=10.0, tx_mm=2.0)  # 1 mm away
    turned = rigid(rz_deg=190.0, tx_mm=1.0)
    T = torch.stack([torch.stack([first, near, far, turned])] * 4)  # (4, 4 starts, 4, 4)
    ok = torch.tensor([[True, True, False, False],  # only the same alignment verified
                       [True, False, True, False],  # verified 1 mm away
                       [True, False, False, True],  # verified half a turn round
                       [False, False, False, False]])
    assert elsewhere(T, ok, MODEL).tolist() == [False, True, True, False]
    assert elsewhere(T, ok, MODEL.scaled(3.0)).tolist() == [False, False, True, False]  # 1 mm within 1.5 mm
    # compared with another result: from the one 1 mm away, the first start is elsewhere
    at = torch.tensor([0, 2, 0, 0])
    assert elsewhere(T, ok, MODEL, at).tolist() == [False, True, True, False]
    assert elsewhere(T[1:2, 1:], ok[1:2, 1:], MODEL, torch.tensor([1])).tolist() == [False]  # alone
    with pytest.raises(ValueError, match="S, 4, 4"):
        elsewhere(T[:, :3], ok, MODEL)


def _backend(kfs, check: bool, trust: bool = False, near: bool = True) -> BackEnd:
    cfg = Config()
    be = BackEnd(replace(cfg, loop=replace(cfg.loop, check_ambiguity=check, trust_repetitive=trust, best_nearby=near)))
    for k in kfs[:3]:
        be.add(k)
    return be


def test_loop_between_groups_on_a_texture_that_verifies_elsewhere_is_held():
    """Two sessions on the crossed-sinusoid dome (``textured``): keyframe 2's SIFT loop to
    session 0 is right, but the pair also verifies from a start half a contact away (12 deg,
    2 mm off); it cannot say where the touch was, so it is dropped between groups like a
    repetitive loop, or kept waiting with ``trust_repetitive``; without the check it waits."""
    kfs, kf0_T = _sessions(textured(0))
    checked, unchecked, trusted = _backend(kfs, True), _backend(kfs, False), _backend(kfs, True, trust=True)
    assert checked.stats.ambiguous_loops == 1 and checked.gate.pending == [] and checked.gate.stats.repetitive == 1
    assert unchecked.stats.ambiguous_loops == 0 and [p.b_id for p in unchecked.gate.pending] == [2]
    assert trusted.stats.ambiguous_loops == 1 and [p.b_id for p in trusted.gate.pending] == [2]
    assert trusted.gate.pending[0].loop.ambiguous and trusted.gate.pending[0].loop.to_dict()["ambiguous"] is True
    assert checked.summary()["ambiguous_loops"] == 1
    # the loop moved to the best-scoring alignment nearby, about as far from the truth
    # (0.299 against 0.275 mm with spread samples; no farther with top-k);
    # without best_nearby (and probes) it keeps its measurement
    assert checked.stats.moved_loops == 1 and _backend(kfs, True, near=False).stats.moved_loops == 0
    p = trusted.gate.pending[0]
    held = _backend(kfs, True, trust=True, near=False).gate.pending[0]
    truth = se3.inverse(kf0_T[p.a_id]) @ kf0_T[p.b_id]
    (rot, trans), (rot0, trans0) = (pose_error(x.a_T_b.double()[None], truth[None]) for x in (p, held))
    assert float(trans) <= float(trans0) + 3e-5 and float(rot) <= float(rot0) + 0.05


def test_the_alternatives_are_verified_without_the_stall_check(monkeypatch):
    """An alternative start that verifies only after a slow climb must still count, so the
    check's batch (12 starts for the one loop between groups) verifies exhaustively, while
    detection's own verification keeps the stall check."""
    kfs, _ = _sessions(textured(0))
    calls, verify = [], LoopDetector.verify

    def spy(self, query, refs, init, exhaustive=False):
        calls.append((len(refs), exhaustive))
        return verify(self, query, refs, init, exhaustive)

    monkeypatch.setattr(LoopDetector, "verify", spy)
    be = _backend(kfs, True)
    assert be.stats.ambiguous_loops == 1
    assert (12, True) in calls and all(not exhaustive for n, exhaustive in calls if n != 12)


def test_loop_between_groups_on_random_bumps_is_not_held():
    kfs, _ = _sessions(speckled(0))
    be = _backend(kfs, True)
    assert be.stats.ambiguous_loops == 0 and [p.b_id for p in be.gate.pending] == [2]
    assert not be.gate.pending[0].loop.ambiguous


def test_ambiguous_loops_are_not_probed():
    """A probe would only corroborate a loop the gate drops: none is tried. (Keyframe 3
    is the query, so keyframe 2 of its session could be probed.)"""
    kfs, _ = _sessions(textured(0))
    cfg = Config()
    be = BackEnd(replace(cfg, loop=replace(cfg.loop, probes=2)))
    for k in kfs:
        be.add(k, detect=k.id != 2)
    assert be.detector.stats.loops >= 1 and be.stats.ambiguous_loops == be.detector.stats.loops
    assert be.stats.probes == 0 and be.group[3] != be.group[0]


def test_best_finds_the_alignment_one_rib_over_that_a_start_one_period_off_misses():
    """Ribs 0.45 mm apart on random bumps: NormalFlow started one period off converges there
    and verifies (the bumps disagree, so with a lower CCS); a near start reaches the truth,
    which scores higher, and :func:`best` takes it."""
    lam = 0.45e-3
    view = rigid(rz_deg=4.0, tx_mm=0.3, ty_mm=-0.2)  # keyframe 0's coordinates into keyframe 1's
    f = frames(replace(speckled(0), waves=[(30e-6, lam, 0.0, 0.0)]), [EYE, view])
    q, c = Keyframe(1, 1, f[1], True, EYE), Keyframe(0, 0, f[0], True, EYE)
    det = LoopDetector(Config())
    fp = det.footprint(q)
    for off_mm in (lam * 1e3, -lam * 1e3):
        res = det.verify(q, [c] * 12, starts(rigid(tx_mm=off_mm) @ view, fp.centre, fp.radius, 0.5e-3))
        rot, trans = pose_error(res.tar_T_ref.double(), view.expand(12, 4, 4))
        assert bool(res.ok[0]) and float(trans[0]) > 0.3  # verified one rib off
        b = int(best(res.ok[None], res.ccs[None])[0])
        assert b in range(NEAR.start, NEAR.stop) and float(res.ccs[b]) > float(res.ccs[0])
        assert float(rot[b]) < 0.05 and float(trans[b]) < 0.01


@pytest.mark.parametrize("near, trans_mm, moved", [(True, 0.3, True), (True, 0.0, True), (False, 0.3, False),
                                                   (True, 1.0, False)])
def test_loop_within_a_group_one_rib_off_enters_the_graph_at_the_truth(monkeypatch, near, trans_mm, moved):
    """Ribs 0.45 mm apart on random bumps, one session: keyframe 2's loop to keyframe 0
    measured one rib off verifies, and agrees with the odometry within the gate's drift
    tolerance, so the gate accepts it. With ``best_nearby`` it differs from the prediction
    by more than 0.3 mm, so it first moves to the near start that reaches the truth;
    without, or when the loop is within ``best_nearby_trans_mm`` of the prediction, it
    enters the graph one rib off (the refinement over every contact pixel stays there too)."""
    lam = 0.45e-3
    views = [EYE, rigid(rz_deg=5.0, tx_mm=1.2), rigid(rz_deg=4.0, tx_mm=0.3, ty_mm=-0.2)]  # 0's coordinates into k's
    f = frames(replace(speckled(0), waves=[(30e-6, lam, 0.0, 0.0)]), views)
    kf0_T = torch.stack([se3.inverse(v) for v in views])
    kfs = [Keyframe(k, 0, f[k], k == 0, EYE if k == 0 else se3.inverse(kf0_T[k - 1]) @ kf0_T[k]) for k in range(3)]
    off = se3.inverse(rigid(tx_mm=lam * 1e3) @ views[2])  # keyframe 2 in keyframe 0, one rib off
    detect = LoopDetector.detect

    def one_rib_off(self, kf, *args):
        found = detect(self, kf, *args)
        return [Loop(0, 2, off, 0.9, 0.9, 20, views[2], False)] if kf.id == 2 else found

    monkeypatch.setattr(LoopDetector, "detect", one_rib_off)
    cfg = Config()
    be = BackEnd(replace(cfg, loop=replace(cfg.loop, best_nearby=near, best_nearby_trans_mm=trans_mm,
                                           best_nearby_rot_deg=5.0 if trans_mm > 0.5 else 1.0)))
    for k in kfs:
        be.add(k)
    (loop,) = [lp for lp in be.loops if (lp.ref_id, lp.tar_id) == (0, 2)]
    rot, trans = pose_error(loop.ref_T_tar.double()[None], kf0_T[2][None])
    if moved:
        assert be.stats.moved_loops == 1 and float(trans) < 0.01 and float(rot) < 0.05  # mm, deg
    else:
        assert be.stats.moved_loops == 0 and float(trans) > 0.3


@pytest.mark.parametrize("surface, flagged", [(textured(0), True), (speckled(0), False)])
def test_loop_within_a_group_off_the_prediction_must_verify_nowhere_else(surface, flagged):
    """One session whose third keyframe returns near the first, with its odometry 2 deg off:
    the loop differs from the prediction, so it is verified from every alternative start
    too. On the crossed-sinusoid dome the pair also verifies half a contact away, so the
    loop is marked ambiguous (the gate then uses it only where it agrees at zero drift, like
    a repetitive one); on random bumps it is not."""
    kfs, kf0_T = _sessions(surface)
    one = [Keyframe(0, 0, kfs[0].maps, True, EYE), Keyframe(1, 0, kfs[1].maps, False, kfs[1].prev_T_kf),
           Keyframe(2, 0, kfs[2].maps, False, se3.inverse(kf0_T[1]) @ kf0_T[2] @ rigid(rz_deg=2.0))]
    be = BackEnd(Config())
    for k in one:
        be.add(k)
    loops = [lp for lp in be.loops if (lp.ref_id, lp.tar_id) == (0, 2)]
    held = [lp for lp, why in be.gate.held() if (lp.ref_id, lp.tar_id) == (0, 2)]
    assert len(loops + held) == 1 and be.stats.ambiguous_loops == int(flagged)
    assert (loops + held)[0].ambiguous == flagged


def test_loops_within_a_group_that_agree_with_the_estimate_are_not_verified_again(monkeypatch):
    """One session on random bumps whose third keyframe returns near the first: its loop
    agrees with the odometry (exact here) to well within 1 deg / 0.3 mm, so it is taken as
    measured; with both thresholds 0 it is verified from every start of
    :func:`~tactile_slam.loop.ambiguity.starts` as well, and stays where it was (the bumps
    have one alignment)."""
    views = [EYE, rigid(rz_deg=5.0, tx_mm=1.2), rigid(rz_deg=4.0, tx_mm=0.3, ty_mm=-0.2)]
    f = frames(speckled(0), views)
    kf0_T = torch.stack([se3.inverse(v) for v in views])
    kfs = [Keyframe(k, 0, f[k], k == 0, EYE if k == 0 else se3.inverse(kf0_T[k - 1]) @ kf0_T[k]) for k in range(3)]
    calls, verify = [], LoopDetector.verify

    def spy(self, query, refs, init, exhaustive=False):
        calls.append(len(refs))
        return verify(self, query, refs, init, exhaustive)

    monkeypatch.setattr(LoopDetector, "verify", spy)
    found = {}
    for limits in ((1.0, 0.3), (0.0, 0.0)):
        cfg, calls[:] = Config(), []
        be = BackEnd(replace(cfg, loop=replace(cfg.loop, best_nearby_rot_deg=limits[0],
                                               best_nearby_trans_mm=limits[1])))
        for k in kfs:
            be.add(k)
        (loop,) = [lp for lp in be.loops if (lp.ref_id, lp.tar_id) == (0, 2)]
        found[limits] = (list(calls), loop.ref_T_tar)
    (strict, T), (every, T0) = found[(1.0, 0.3)], found[(0.0, 0.0)]
    assert 12 not in strict and every.count(12) == 1 and len(every) == len(strict) + 1
    rot, trans = pose_error(T0.double()[None], T.double()[None])
    assert float(rot) < 0.05 and float(trans) < 0.01  # deg, mm
    with pytest.raises(ValueError, match="best_nearby"):
        BackEnd(replace(Config(), loop=replace(Config().loop, best_nearby_trans_mm=-0.1)))
