"""The back end re-measures accepted loops over every contact pixel (posegraph.refine_loops)."""

from __future__ import annotations

from dataclasses import replace

import pytest
import torch

from tactile_slam.backend import BackEnd
from tactile_slam.config import Config
from tactile_slam.posegraph import se3
from tactile_slam.registration.refine import pressed_core, refine_edges
from tactile_slam.registration.result import pose_error
from tests.loop.revisit import revisit_keyframes


@pytest.fixture(scope="module")
def revisit():
    """The revisit scene (:func:`tests.loop.revisit.revisit_keyframes`) with slopes carrying
    i.i.d. noise of 0.05, so the 3000-sample verification is measurably off."""
    return revisit_keyframes(0.05)


def _run(kfs, **posegraph):
    cfg = Config()
    be = BackEnd(replace(cfg, posegraph=replace(cfg.posegraph, **posegraph)))
    for k in kfs:
        be.add(k)
    return be


def test_accepted_loops_are_refined_and_enter_the_graph(revisit):
    kfs, kf0_T = revisit
    cfg = Config()
    plain, refined = _run(kfs, refine_loops=False), _run(kfs, refine_loops=True)
    assert len(plain.loops) >= 1 and [(lp.ref_id, lp.tar_id) for lp in plain.loops] == \
        [(lp.ref_id, lp.tar_id) for lp in refined.loops]
    assert refined.stats.refined == len(refined.loops) and plain.stats.refined == 0
    assert refined.summary()["refined_loops"] == len(refined.loops)
    for a, b in zip(plain.loops, refined.loops):
        # the factor is NormalFlow over every pixel of the pressed core from the verified
        # measurement (test_refine.py shows it is the more accurate one)
        core = [pressed_core(kfs[i].frame, cfg.depth_test, cfg.contact.height_percentile)
                for i in (a.ref_id, a.tar_id)]
        expected, ok = refine_edges(core[:1], core[1:], a.ref_T_tar[None], refined.detector.nf_config)
        assert bool(ok[0]) and not torch.equal(b.ref_T_tar, a.ref_T_tar)
        torch.testing.assert_close(b.ref_T_tar, expected[0])
        truth = (se3.inverse(kf0_T[a.ref_id]) @ kf0_T[a.tar_id])[None]
        rot_b, trans_b = pose_error(b.ref_T_tar[None], truth)
        assert float(rot_b) < 0.3 and float(trans_b) < 0.01
    e = refined.graph.edges
    loop_Z = e.Z[e.loop]
    torch.testing.assert_close(loop_Z, torch.stack([lp.ref_T_tar for lp in refined.loops]))


def test_loops_refined_over_the_whole_contact_without_refine_core(revisit):
    kfs, _ = revisit
    be, plain = _run(kfs, refine_core=False), _run(kfs, refine_loops=False)
    assert len(be.loops) >= 1
    for lp in be.loops:
        first = next(x for x in plain.loops if (x.ref_id, x.tar_id) == (lp.ref_id, lp.tar_id))
        expected, _ = refine_edges([kfs[lp.ref_id].frame], [kfs[lp.tar_id].frame], first.ref_T_tar[None],
                                   be.detector.nf_config)
        torch.testing.assert_close(lp.ref_T_tar, expected[0])


def test_only_sift_loops_keep_the_sift_measurement(revisit):
    kfs, _ = revisit
    cfg = Config()
    be = BackEnd(cfg, loop_mode="only_sift")
    for k in kfs:
        be.add(k)
    assert len(be.loops) >= 1 and be.stats.refined == 0


def test_bad_refine_budget_is_refused():
    cfg = Config()
    with pytest.raises(ValueError, match="refine_n_samples"):
        BackEnd(replace(cfg, posegraph=replace(cfg.posegraph, refine_n_samples=0)))
