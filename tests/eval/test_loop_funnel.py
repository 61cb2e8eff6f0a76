"""revisit_funnel: the stages of loop detection that true revisits between sessions reach."""

import dataclasses

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from tactile_slam.config import Config
from tactile_slam.eval.loop_funnel import STAGES, revisit_funnel
from tactile_slam.tracking.keyframe import Keyframe
from tests.loop.revisit import revisit_keyframes
from tests.registration.surfaces import Surface, frames, rigid


def three_sessions() -> tuple[list[Keyframe], np.ndarray]:
    """The revisit scene's three textured keyframes, each its own session."""
    kfs, kf0_T = revisit_keyframes()
    return [dataclasses.replace(k, session=i) for i, k in enumerate(kfs)], kf0_T.numpy()


def test_textured_revisits_reach_every_stage():
    kfs, truth = three_sessions()
    counts = revisit_funnel(kfs, truth, Config())
    assert tuple(counts) == STAGES
    assert all(counts[s] == 3 for s in STAGES)  # all three pairs share surface, each verifies correctly


def test_correct_is_judged_against_the_truth():
    """With keyframe 2 placed 3 degrees off in the given truth, its two pairs still match
    and verify (the data did not change) but are no longer counted correct."""
    kfs, truth = three_sessions()
    turn = np.eye(4)
    turn[:3, :3] = Rotation.from_euler("z", 3.0, degrees=True).as_matrix()
    truth[2] = truth[2] @ turn
    counts = revisit_funnel(kfs, truth, Config())
    assert counts["verified"] == 3 and counts["correct"] == 1


def test_pairs_within_a_session_and_textureless_touches_are_not_counted_as_reached():
    kfs, truth = three_sessions()
    one = [dataclasses.replace(k, session=0) for k in kfs]
    assert revisit_funnel(one, truth, Config()) == dict.fromkeys(STAGES, 0)
    # a smooth dome in two sessions: the pair shares surface, but SIFT finds nothing to match
    views = [torch.eye(4, dtype=torch.float64), rigid(rz_deg=5.0, tx_mm=0.5)]
    f = frames(Surface(), views)
    smooth = [Keyframe(i, i, f[i], True, torch.eye(4, dtype=torch.float64)) for i in range(2)]
    poses = torch.stack([torch.linalg.inv(v) for v in views]).numpy()
    counts = revisit_funnel(smooth, poses, Config())
    assert counts["pairs"] == 1 and counts["keypoints"] == 0 and counts["correct"] == 0


def test_one_pose_per_keyframe():
    assert revisit_funnel([], np.zeros((0, 4, 4)), Config()) == dict.fromkeys(STAGES, 0)  # no keyframes: nothing
    kfs, truth = three_sessions()
    with pytest.raises(ValueError, match="one pose per keyframe"):
        revisit_funnel(kfs, truth[:2], Config())
