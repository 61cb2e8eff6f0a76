"""Keyframes without undeformed gel in view: the back end marks their loops and counts them."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest
import torch

from tactile_slam.backend import BackEnd
from tactile_slam.bench.loops import loop_error
from tactile_slam.config import Config
from tactile_slam.posegraph import se3
from tactile_slam.tracking.keyframe import Keyframe
from tests.loop.revisit import revisit_keyframes


@pytest.fixture(scope="module")
def revisit():
    """One session: keyframe 0, keyframe 1 moved away, keyframe 2 back near 0 (a loop to 0);
    ``kf0_T`` ``(3, 4, 4)`` each keyframe's true pose in keyframe 0's frame."""
    return revisit_keyframes()


def _guessed_zero(kf: Keyframe, offset_px: float) -> Keyframe:
    """The keyframe as if its gel were covered: heights shifted by a wrong zero, depth unknown."""
    maps = replace(kf.frame, height=kf.frame.height + offset_px, depth_known=torch.tensor([False]))
    return Keyframe(kf.id, kf.session, maps, kf.new_session, kf.prev_T_kf)


def test_loops_through_a_keyframe_of_unknown_depth_are_marked(revisit, tmp_path):
    kfs, kf0_T = revisit
    known = BackEnd(Config())
    for k in kfs:
        known.add(k)
    assert [(lp.ref_id, lp.tar_id) for lp in known.loops] == [(0, 2)] and known.loops[0].depth_known
    assert known.summary()["keyframes_depth_unknown"] == 0

    offset_px = 0.2 / kfs[0].frame.mm_per_px  # keyframe 0's zero guessed 0.2 mm off
    guessed = [_guessed_zero(kfs[0], offset_px)] + kfs[1:]
    be = BackEnd(Config())
    for k in guessed:
        be.add(k)
    assert not guessed[0].depth_known and guessed[1].depth_known
    assert be.summary()["keyframes_depth_unknown"] == 1
    (lp,) = be.loops
    assert (lp.ref_id, lp.tar_id) == (0, 2) and not lp.depth_known
    be.write(tmp_path)
    assert json.loads((tmp_path / "loops.json").read_text())[0]["depth_known"] is False

    # the loop's z carries the wrong zero (NormalFlow's z is the mean height difference);
    # across the sensor axis it is as accurate as with the true zero
    truth = se3.inverse(kf0_T[0]) @ kf0_T[2]
    dz_mm = float(lp.ref_T_tar[2, 3] - known.loops[0].ref_T_tar[2, 3]) * 1e3
    assert dz_mm == pytest.approx(0.2, abs=0.02)
    kmap = {k.id: k for k in guessed}
    rot, trans = loop_error(lp, truth, kmap)
    rot_known, trans_known = loop_error(known.loops[0], truth, {k.id: k for k in kfs})
    assert rot == pytest.approx(rot_known, abs=1e-3) and trans < 0.02 and trans_known < 0.02
    full = float(torch.linalg.vector_norm(lp.ref_T_tar[:3, 3] - truth[:3, 3])) * 1e3
    assert full > 0.15 and np.isclose(trans, float(torch.linalg.vector_norm(lp.ref_T_tar[:2, 3] - truth[:2, 3])) * 1e3)
