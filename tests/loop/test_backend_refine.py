"""The back end re-measures verified loops over every contact pixel of both keyframes
(posegraph.refine_loops, refine_both_ways) and holds those whose two measurements disagree
(loop.max_asymmetry_deg / max_asymmetry_mm)."""

from __future__ import annotations

from dataclasses import replace

import pytest
import torch

from tactile_slam.backend import BackEnd, asymmetric
from tactile_slam.config import Config
from tactile_slam.posegraph import se3
from tactile_slam.registration.refine import BothWays, pressed_core, refine_both_ways, refine_edges
from tactile_slam.registration.result import pose_error
from tests.loop.revisit import revisit_keyframes
from tests.registration.surfaces import rigid


@pytest.fixture(scope="module")
def revisit():
    """The revisit scene (:func:`tests.loop.revisit.revisit_keyframes`) with slopes carrying
    i.i.d. noise of 0.05, so the 3000-sample verification is measurably off."""
    return revisit_keyframes(0.05)


def _run(kfs, loop=None, **posegraph):
    cfg = Config()
    be = BackEnd(replace(cfg, posegraph=replace(cfg.posegraph, **posegraph), loop=replace(cfg.loop, **(loop or {}))))
    for k in kfs:
        be.add(k)
    return be


def test_verified_loops_are_measured_both_ways_and_enter_the_graph(revisit):
    kfs, kf0_T = revisit
    cfg = Config()
    plain, refined = _run(kfs, refine_loops=False), _run(kfs, refine_loops=True)
    assert len(plain.loops) >= 1 and [(lp.ref_id, lp.tar_id) for lp in plain.loops] == \
        [(lp.ref_id, lp.tar_id) for lp in refined.loops]
    assert refined.stats.refined == len(refined.loops) and plain.stats.refined == 0
    assert refined.summary()["refined_loops"] == len(refined.loops)
    assert refined.summary()["asymmetric_loops"] == 0 and len(refined.stats.time_refine) == len(kfs)
    for a, b in zip(plain.loops, refined.loops):
        # the factor is NormalFlow over every pixel of both pressed cores from the verified
        # measurement (test_refine.py shows it is the more accurate one)
        core = [pressed_core(kfs[i].frame, cfg.depth_test, cfg.contact.height_percentile)
                for i in (a.ref_id, a.tar_id)]
        both = refine_both_ways(core[:1], core[1:], a.ref_T_tar[None], refined.detector.nf_config)
        assert bool(both.forward_ok[0] & both.reverse_ok[0]) and not torch.equal(b.ref_T_tar, a.ref_T_tar)
        torch.testing.assert_close(b.ref_T_tar, both.ref_T_tar[0])
        truth = (se3.inverse(kf0_T[a.ref_id]) @ kf0_T[a.tar_id])[None]
        rot_b, trans_b = pose_error(b.ref_T_tar[None], truth)
        assert float(rot_b) < 0.3 and float(trans_b) < 0.01
    e = refined.graph.edges
    loop_Z = e.Z[e.loop]
    torch.testing.assert_close(loop_Z, torch.stack([lp.ref_T_tar for lp in refined.loops]))


def test_one_way_refinement_is_the_forward_measurement(revisit):
    kfs, _ = revisit
    cfg = Config()
    be, plain = _run(kfs, refine_both_ways=False), _run(kfs, refine_loops=False)
    assert len(be.loops) == len(plain.loops) >= 1
    for a, b in zip(plain.loops, be.loops):
        core = [pressed_core(kfs[i].frame, cfg.depth_test, cfg.contact.height_percentile)
                for i in (a.ref_id, a.tar_id)]
        expected, ok = refine_edges(core[:1], core[1:], a.ref_T_tar[None], be.detector.nf_config)
        assert bool(ok[0])
        torch.testing.assert_close(b.ref_T_tar, expected[0])


def test_loops_whose_two_measurements_disagree_are_held(revisit):
    """Two measurements never agree exactly: with no tolerance every loop is held, with a
    reason and its value, and the keyframes stay in their sessions' groups."""
    kfs, _ = revisit
    plain = _run(kfs)
    strict = _run(kfs, loop={"max_asymmetry_deg": 0.0})
    assert len(plain.loops) >= 1 and strict.loops == [] and strict.summary()["asymmetric_loops"] == len(plain.loops)
    held = [h for h in strict.held_loops() if h["reason"] == "asymmetric"]
    assert sorted((h["ref_id"], h["tar_id"]) for h in held) == sorted((lp.ref_id, lp.tar_id) for lp in plain.loops)
    assert strict.graph.edges.loop.sum() == 0
    assert len(_run(kfs, loop={"max_asymmetry_mm": 0.0}).loops) == 0
    unlimited = _run(kfs, loop={"max_asymmetry_deg": None, "max_asymmetry_mm": None})
    assert [(lp.ref_id, lp.tar_id) for lp in unlimited.loops] == [(lp.ref_id, lp.tar_id) for lp in plain.loops]


def _both(forward: torch.Tensor, reverse: torch.Tensor) -> BothWays:
    ok = torch.ones(len(forward), dtype=torch.bool)
    return BothWays(forward, forward, reverse, ok, ok)


def test_asymmetry_rule():
    eye = torch.eye(4, dtype=torch.float64).repeat(6, 1, 1)
    reverse = torch.stack([rigid(rz_deg=0.9), rigid(rz_deg=1.1), rigid(rx_deg=3.0), rigid(rx_deg=3.0),
                           rigid(tx_mm=0.31), rigid(rz_deg=0.5, tx_mm=0.2)])
    sigma = [None, None, None, 5.44, None, 5.44]
    assert asymmetric(_both(eye, reverse), sigma, 1.0, 0.3).tolist() == [False, True, True, False, True, False]
    # the tilt sigma widens only the out-of-plane part: a twist beyond max_deg is held either way
    assert asymmetric(_both(eye[:1], rigid(rz_deg=1.5)[None]), [5.44], 1.0, 0.3).tolist() == [True]
    assert asymmetric(_both(eye, reverse), sigma, None, None).tolist() == [False] * 6
    bad_rot, bad_trans = reverse.clone(), reverse.clone()
    bad_rot[0, 0, 0] = bad_trans[0, 0, 3] = float("nan")
    assert asymmetric(_both(eye, bad_rot), sigma, 1.0, None)[0]
    assert asymmetric(_both(eye, bad_trans), sigma, None, 0.3)[0]


def test_loops_refined_over_the_whole_contact_without_refine_core(revisit):
    kfs, _ = revisit
    be, plain = _run(kfs, refine_core=False), _run(kfs, refine_loops=False)
    assert len(be.loops) >= 1
    for lp in be.loops:
        first = next(x for x in plain.loops if (x.ref_id, x.tar_id) == (lp.ref_id, lp.tar_id))
        both = refine_both_ways([kfs[lp.ref_id].frame], [kfs[lp.tar_id].frame], first.ref_T_tar[None],
                                be.detector.nf_config)
        torch.testing.assert_close(lp.ref_T_tar, both.ref_T_tar[0])


def test_only_sift_loops_keep_the_sift_measurement(revisit):
    kfs, _ = revisit
    cfg = Config()
    be = BackEnd(cfg, loop_mode="only_sift")
    for k in kfs:
        be.add(k)
    assert len(be.loops) >= 1 and be.stats.refined == 0


def test_bad_refine_budget_and_asymmetry_limits_are_refused():
    cfg = Config()
    with pytest.raises(ValueError, match="refine_n_samples"):
        BackEnd(replace(cfg, posegraph=replace(cfg.posegraph, refine_n_samples=0)))
    for name in ("max_asymmetry_deg", "max_asymmetry_mm"):
        for bad in (-1.0, float("nan")):
            with pytest.raises(ValueError, match=name):
                BackEnd(replace(cfg, loop=replace(cfg.loop, **{name: bad})))
