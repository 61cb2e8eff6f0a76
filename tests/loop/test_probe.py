"""Probes (tactile_slam/loop/probe.py; BackEnd with loop.probes): pair choice, the
alternative starts, and a second session joined through a predicted pair."""

from __future__ import annotations

import math
from dataclasses import replace

import pytest
import torch

from tactile_slam.backend import BackEnd
from tactile_slam.config import Config
from tactile_slam.loop.probe import best_pair, disc_overlap
from tactile_slam.posegraph import se3
from tactile_slam.registration.result import pose_error
from tactile_slam.tracking.keyframe import Keyframe
from tests.registration.surfaces import Surface, frames, rigid, speckled, textured

EYE = torch.eye(4, dtype=torch.float64)


def _mc_overlap(d: float, r1: float, r2: float, n: int = 801) -> float:
    """Grid estimate of the discs' intersection over the smaller disc's area."""
    small, big = sorted((r1, r2))
    u = torch.linspace(-small, small, n, dtype=torch.float64)
    x, y = torch.meshgrid(u, u, indexing="ij")
    in_small = x**2 + y**2 <= small**2
    in_big = (x - d) ** 2 + y**2 <= big**2
    return float((in_small & in_big).sum() / in_small.sum())


@pytest.mark.parametrize("d, r1, r2", [(1.0, 1.0, 1.0), (1.5, 2.0, 1.0), (0.4, 0.5, 3.0), (2.9, 1.0, 2.0)])
def test_disc_overlap_matches_a_grid_estimate(d, r1, r2):
    got = float(disc_overlap(torch.tensor(d), torch.tensor(r1), torch.tensor(r2)))
    assert got == pytest.approx(_mc_overlap(d, r1, r2), abs=5e-3)
    assert got == pytest.approx(float(disc_overlap(torch.tensor(d), torch.tensor(r2), torch.tensor(r1))))


def test_disc_overlap_limits_and_broadcasting():
    out = disc_overlap(torch.tensor([0.0, 0.5, 3.0, 10.0]), torch.tensor(1.0), torch.tensor([1.0, 2.0, 2.0, 2.0]))
    assert out.dtype == torch.float64 and out.shape == (4,)
    torch.testing.assert_close(out, torch.tensor([1.0, 1.0, 0.0, 0.0], dtype=torch.float64))
    assert disc_overlap(torch.zeros(2, 3), torch.ones(2, 1), torch.ones(3)).shape == (2, 3)


def _line(xs_mm: list[float]) -> torch.Tensor:
    return torch.stack([rigid(tx_mm=x) for x in xs_mm])


def test_best_pair_picks_the_most_overlapping_allowed_pair():
    """H's keyframes at x = 0, 3, 6 mm, G's at 0 and 2 mm of G's frame, G placed 3 mm along x:
    G's first keyframe lands on H's second."""
    H_T_G = rigid(tx_mm=3.0)
    c3, r = torch.zeros(3, 3, dtype=torch.float64), torch.full((3,), 1.5e-3, dtype=torch.float64)
    c2, r2 = torch.zeros(2, 3, dtype=torch.float64), torch.full((2,), 1.5e-3, dtype=torch.float64)
    allowed = torch.ones(3, 2, dtype=torch.bool)
    assert best_pair(H_T_G, _line([0, 3, 6]), c3, r, _line([0, 2]), c2, r2, allowed) == (1, 0)
    allowed[1, 0] = False  # already probed: the next best is G's second keyframe at 5 mm vs H's at 6 mm
    assert best_pair(H_T_G, _line([0, 3, 6]), c3, r, _line([0, 2]), c2, r2, allowed) == (2, 1)
    # the contact centre counts, not the sensor origin
    off = c2.clone()
    off[0, 0] = 3.0e-3  # G's first contact sits 3 mm right of its sensor: lands at 6 mm
    assert best_pair(H_T_G, _line([0, 3, 6]), c3, r, _line([0, 2]), off, r2, torch.ones(3, 2, dtype=torch.bool)) \
        == (2, 0)


def test_best_pair_none_when_apart_or_facing_away():
    c, r = torch.zeros(1, 3, dtype=torch.float64), torch.full((1,), 1e-3, dtype=torch.float64)
    ok = torch.ones(1, 1, dtype=torch.bool)
    assert best_pair(rigid(tx_mm=5.0), EYE[None], c, r, EYE[None], c, r, ok) is None
    assert best_pair(rigid(rx_deg=180.0), EYE[None], c, r, EYE[None], c, r, ok) is None
    assert best_pair(EYE, EYE[None], c, r, EYE[None], c, r, ~ok) is None
    empty = torch.zeros(0, 4, 4, dtype=torch.float64)
    assert best_pair(EYE, empty, c[:0], r[:0], EYE[None], c, r, torch.ones(0, 1, dtype=torch.bool)) is None


def test_best_pair_skips_pairs_with_non_finite_poses_or_footprints():
    c, r = torch.zeros(2, 3, dtype=torch.float64), torch.full((2,), 1.5e-3, dtype=torch.float64)
    ok = torch.ones(2, 2, dtype=torch.bool)
    bad = _line([0, 0]).clone()
    bad[0, 0, 3] = math.nan  # H's first pose unknown: only its second keyframe can pair
    assert best_pair(EYE, bad, c, r, _line([0, 3]), c, r, ok) == (1, 0)
    nan_r = r.clone()
    nan_r[:] = math.nan
    assert best_pair(EYE, _line([0, 0]), c, nan_r, _line([0, 3]), c, r, ok) is None


def test_best_pair_refuses_bad_shapes():
    c, r = torch.zeros(2, 3, dtype=torch.float64), torch.ones(2, dtype=torch.float64)
    with pytest.raises(ValueError, match="poses"):
        best_pair(EYE[:3], EYE.expand(2, 4, 4), c, r, EYE.expand(2, 4, 4), c, r, torch.ones(2, 2, dtype=torch.bool))
    with pytest.raises(ValueError, match="centres"):
        best_pair(EYE, EYE.expand(2, 4, 4), c[:, :2], r, EYE.expand(2, 4, 4), c, r, torch.ones(2, 2, dtype=torch.bool))
    with pytest.raises(ValueError, match="allowed"):
        best_pair(EYE, EYE.expand(2, 4, 4), c, r, EYE.expand(2, 4, 4), c, r, torch.ones(2, 3, dtype=torch.bool))


def _sessions(surface: Surface):
    """Session 0: keyframes 0 (the reference view) and 1; session 1: keyframe 2 near 0 (its
    SIFT loop reaches session 0) and keyframe 3 near 1. Poses: keyframe k in keyframe 0's frame."""
    views = [EYE, rigid(rz_deg=5.0, tx_mm=1.2), rigid(rx_deg=1.0, rz_deg=-3.0, ty_mm=0.3),
             rigid(rz_deg=7.0, tx_mm=1.0, ty_mm=0.4)]
    f = frames(surface, views)
    kf0_T = torch.stack([se3.inverse(v) for v in views])
    kfs = [Keyframe(0, 0, f[0], True, EYE), Keyframe(1, 0, f[1], False, se3.inverse(kf0_T[0]) @ kf0_T[1]),
           Keyframe(2, 1, f[2], True, EYE), Keyframe(3, 1, f[3], False, se3.inverse(kf0_T[2]) @ kf0_T[3])]
    return kfs, kf0_T


@pytest.fixture(scope="module")
def two_sessions():
    return _sessions(speckled(0))


def _backend(kfs, probes: int, check_ambiguity: bool = True) -> BackEnd:
    cfg = Config()
    be = BackEnd(replace(cfg, loop=replace(cfg.loop, probes=probes, check_ambiguity=check_ambiguity)))
    for k in kfs:
        be.add(k, detect=k.id != 3)  # keyframe 3 finds nothing itself: only a probe can reach it
    return be


def test_probe_joins_a_second_session_that_one_query_could_not(two_sessions):
    kfs, kf0_T = two_sessions
    without = _backend(kfs, probes=0)
    assert without.detector.stats.loops >= 1 and {p.b_id for p in without.gate.pending} == {2}
    assert without.group[3] != without.group[0] and without.stats.probes == 0
    be = _backend(kfs, probes=1)
    assert be.stats.probes == be.stats.probe_loops == 1 and be.stats.probes_ambiguous == 0
    assert be.group[3] == be.group[0] and be.stats.merges == 1
    probes = [lp for lp in be.loops if lp.probe]
    assert len(probes) == 1 and probes[0].tar_id == 3 and probes[0].inliers == 0
    lp = probes[0]
    rot, trans = pose_error(lp.ref_T_tar[None], (se3.inverse(kf0_T[lp.ref_id]) @ kf0_T[3])[None])
    assert float(rot) < 0.2 and float(trans) < 0.01
    # the merged session sits where it belongs: keyframe 3 relative to keyframe 0
    rot, trans = pose_error((se3.inverse(be.start_T_kf[0]) @ be.start_T_kf[3])[None], kf0_T[3][None])
    assert float(rot) < 0.2 and float(trans) < 0.01
    assert be.summary()["probe_loops"] == 1 and lp.to_dict()["probe"] is True


def test_probe_from_a_wrong_prediction_fails(two_sessions):
    """The same pair, with the two sessions placed 1.5 mm and 20 deg off: nothing verifies
    there, so no loop (a false loop between the groups would be refuted the same way)."""
    kfs, kf0_T = two_sessions
    be = _backend(kfs[:3], probes=0)
    be.add(kfs[3], detect=False)
    true_H_T_G = be.start_T_kf[0] @ kf0_T[2] @ se3.inverse(be.start_T_kf[2])
    assert be._probe_pair(1, 3, true_H_T_G) is not None
    assert be._probe_pair(1, 3, rigid(rz_deg=20.0, tx_mm=1.5) @ true_H_T_G) is None


def test_negative_probe_count_is_refused():
    with pytest.raises(ValueError, match="loop.probes"):
        BackEnd(replace(Config(), loop=replace(Config().loop, probes=-1)))


def test_probe_on_a_texture_that_verifies_from_far_starts_is_refused():
    """Waves of four directions (``textured``): NormalFlow started half a contact radius away,
    or half a turn about the contact centre, also verifies, at a pose millimetres off; a
    verification that passes wherever it starts is no evidence, so the probe is refused and
    the sessions stay apart. (With ``loop.check_ambiguity`` the SIFT loop itself is held for
    the same reason, ``test_ambiguity.py``; here it is off so that a probe is tried.)"""
    kfs, _ = _sessions(textured(0))
    be = _backend(kfs, probes=1, check_ambiguity=False)
    assert {p.b_id for p in be.gate.pending} == {2}  # the SIFT loop, waiting
    assert be.stats.probes == 1 and be.stats.probe_loops == 0 and be.stats.probes_ambiguous == 1
    assert be.group[3] != be.group[0] and not any(lp.probe for lp in be.loops)
