"""Matching, 2-D similarity RANSAC and the SE(3) lift."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
import torch

from tactile_slam.loop.features import Features, curvature_features
from tactile_slam.loop.matching import (
    MatchingError, RansacSettings, estimate_similarity, match, match_descriptors, self_similarity, similarity_to_se3,
)
from tactile_slam.registration.result import pose_error
from tests.registration.surfaces import Surface, frames, rigid, textured

S = 0.0634e-3
SHAPE = (240, 320)


def test_translation_sign_convention():
    """A target pattern shifted by +dx px gives +dx s in x (method.md 1.4)."""
    T = similarity_to_se3(np.array([[1.0, 0.0, 5.0], [0.0, 1.0, -3.0]]), SHAPE, S)
    assert T.dtype == torch.float64 and T.shape == (4, 4)
    torch.testing.assert_close(T[:3, :3], torch.eye(3, dtype=torch.float64))
    torch.testing.assert_close(T[:3, 3], torch.tensor([5 * S, -3 * S, 0.0], dtype=torch.float64))


@pytest.mark.parametrize("scale", [1.0, 1.05])
def test_rotation_about_centre_has_no_translation(scale):
    th = math.radians(30)
    c = np.array([(SHAPE[1] - 1) / 2, (SHAPE[0] - 1) / 2])
    A = scale * np.array([[math.cos(th), -math.sin(th)], [math.sin(th), math.cos(th)]])
    M = np.concatenate([A, (c - A @ c)[:, None]], 1)
    T = similarity_to_se3(M, SHAPE, S)
    torch.testing.assert_close(T[:2, 3], torch.zeros(2, dtype=torch.float64), atol=1e-15, rtol=0)
    torch.testing.assert_close(T[:2, :2], torch.as_tensor(A / scale))
    assert abs(float(torch.linalg.det(T[:3, :3])) - 1.0) < 1e-12


def test_lift_matches_metric_map():
    """For pixel points, the lifted transform maps their metric points like M maps pixels."""
    th = math.radians(-17)
    A = np.array([[math.cos(th), -math.sin(th)], [math.sin(th), math.cos(th)]])
    M = np.concatenate([A, np.array([[12.5], [-4.0]])], 1)
    T = similarity_to_se3(M, SHAPE, S)
    px = np.array([[0.0, 0.0], [319.0, 239.0], [100.0, 50.0]])
    tar_px = px @ A.T + M[:, 2]
    c = np.array([(SHAPE[1] - 1) / 2, (SHAPE[0] - 1) / 2])
    P = torch.as_tensor(np.c_[(px - c) * S, np.zeros(3), np.ones(3)])
    expected = (tar_px - c) * S
    torch.testing.assert_close((P @ T.T)[:, :2], torch.as_tensor(expected), atol=1e-12, rtol=0)


def test_cross_check_matches_independent():
    g = np.random.default_rng(0)
    ref, tar = g.random((40, 128), np.float32), g.random((55, 128), np.float32)
    pairs = match_descriptors(ref, tar)
    d = ((ref[:, None] - tar[None]) ** 2).sum(-1)
    fwd, bwd = d.argmin(1), d.argmin(0)
    expected = {(i, int(fwd[i])) for i in range(len(ref)) if bwd[fwd[i]] == i}
    assert {tuple(p) for p in pairs.tolist()} == expected
    assert match_descriptors(ref[:0], tar).shape == (0, 2)


def test_recovers_image_rotation_and_translation():
    """A known 2-D rotation + translation of a curvature map is recovered within
    0.3 degrees and 1 px."""
    fr = frames(textured(1), [torch.eye(4, dtype=torch.float64)])
    curv, contact = fr.curvature[0].numpy(), fr.contact[0].numpy().astype(np.uint8)
    c = ((SHAPE[1] - 1) / 2, (SHAPE[0] - 1) / 2)
    M_true = cv2.getRotationMatrix2D(c, 23.0, 1.0)
    M_true[:, 2] += (6.0, -9.0)
    warp = lambda img, flag: cv2.warpAffine(img, M_true, SHAPE[::-1], flags=flag)  # noqa: E731
    ref = curvature_features(fr.curvature[0], fr.contact[0], 0.7)
    tar = curvature_features(torch.from_numpy(warp(curv, cv2.INTER_LINEAR)),
                             torch.from_numpy(warp(contact, cv2.INTER_NEAREST)).bool(), 0.7)
    sim = match(ref, tar)
    assert sim is not None and sim.inliers >= 8
    angle = math.degrees(math.atan2(sim.M[1, 0], sim.M[0, 0]))
    true_angle = math.degrees(math.atan2(M_true[1, 0], M_true[0, 0]))
    assert abs(angle - true_angle) < 0.3
    pts = np.array([[60.0, 40.0], [160.0, 120.0], [260.0, 200.0]])
    err = np.linalg.norm(pts @ sim.M[:, :2].T + sim.M[:, 2] - (pts @ M_true[:, :2].T + M_true[:, 2]), axis=1)
    assert err.max() < 1.0


def test_lifted_estimate_close_to_rigid_ground_truth():
    """On frames of a rigid in-plane motion, matching + lift is close to the true
    tar_T_ref (a coarse initial guess: within 1 degree and 0.1 mm)."""
    T = rigid(rz_deg=-35, tx_mm=1.2, ty_mm=0.7)
    fr = frames(textured(2), [torch.eye(4, dtype=torch.float64), T])
    sim = match(curvature_features(fr.curvature[0], fr.contact[0], 0.7),
                curvature_features(fr.curvature[1], fr.contact[1], 0.7))
    assert sim is not None
    rot, trans = pose_error(similarity_to_se3(sim.M, SHAPE, S)[None], T[None])
    assert float(rot) < 1.0 and float(trans) < 0.1 + abs(float(T[2, 3])) * 1e3


def test_too_few_matches_is_none():
    g = np.random.default_rng(1)
    pts = g.random((7, 2)) * 100
    assert estimate_similarity(pts, pts + 3.0) is None
    sim = estimate_similarity(g.random((20, 2)) * 100, g.random((20, 2)) * 100, RansacSettings())
    assert sim is None or sim.inliers >= 8


def test_ambiguous_alignment_is_rejected():
    """Matches supporting two distinct alignments (a periodic texture matched at two
    period shifts) give no candidate; a unique alignment with outliers is kept."""
    g = np.random.default_rng(2)
    ref = g.random((24, 2)) * 150 + 50
    tar = ref + np.where(np.arange(24)[:, None] % 2 == 0, [5.0, 0.0], [25.0, 0.0])
    assert estimate_similarity(ref, tar) is None
    sim = estimate_similarity(ref, tar, RansacSettings(ambiguity_ratio=None))
    assert sim is not None and sim.inliers == 12
    unique = ref + [5.0, 0.0]
    unique[:5] = g.random((5, 2)) * 200
    sim = estimate_similarity(ref, unique)
    assert sim is not None and sim.inliers >= 19 and sim.second < 4


def test_self_similarity_of_a_pattern_that_appears_twice():
    """Twelve keypoints and the same pattern again 65 px away (descriptors equal up to
    noise): the texture maps onto itself by that shift; the same points with unrelated
    descriptors do not, nor do fewer keypoints than RANSAC's minimum."""
    g = torch.Generator().manual_seed(0)
    pts = torch.rand(12, 2, generator=g) * 50 + 40
    desc = torch.rand(12, 128, generator=g)
    xy = torch.cat([pts, pts + torch.tensor([60.0, 25.0])])
    twice = torch.cat([desc, desc + 1e-3 * torch.rand(12, 128, generator=g)])
    sim = self_similarity(Features(xy, twice))
    assert sim is not None and sim.inliers >= 8
    assert np.allclose(sim.M[:, :2], np.eye(2), atol=1e-3)
    assert np.allclose(np.abs(sim.M[:, 2]), [60.0, 25.0], atol=0.1)
    assert self_similarity(Features(xy, torch.rand(24, 128, generator=g))) is None
    assert self_similarity(Features(xy[:5], twice[:5])) is None  # fewer than min_inliers


@pytest.mark.parametrize("pairs, flagged", [(4, False), (7, False), (8, True)])
def test_self_similarity_counts_keypoint_pairs_not_directions(pairs, flagged):
    """Keypoints in pairs placed point-symmetrically about one centre, each pair with its own
    shared descriptor (as the rim of a round contact gives after SIFT's orientation
    normalisation): a half turn maps every pair onto itself in both directions. Four pairs
    give the 8 correspondences RANSAC needs, but only 4 distinct pairs: not a repeating
    texture. Eight pairs are."""
    g = torch.Generator().manual_seed(1)
    centre = torch.tensor([160.0, 120.0])
    ang = torch.rand(pairs, generator=g) * math.pi
    rad = 20.0 + 60.0 * torch.rand(pairs, generator=g)
    off = torch.stack([torch.cos(ang), torch.sin(ang)], 1) * rad[:, None]
    xy = torch.cat([centre + off, centre - off])
    desc = torch.rand(pairs, 128, generator=g) * 10
    feats = Features(xy, torch.cat([desc, desc + 1e-3 * torch.rand(pairs, 128, generator=g)]))
    sim = self_similarity(feats)
    assert (sim is not None) == flagged
    if flagged:
        assert sim.inliers == pairs and np.allclose(sim.M[:, :2], -np.eye(2), atol=1e-3)


def test_self_similarity_on_rendered_textures():
    """A square-lattice texture (1 mm waves along x and y) maps onto itself by a symmetry of
    the lattice (a quarter turn or a whole-period shift, unit scale); random waves and
    bumps (seeds 0 and 3) do not."""
    lattice = Surface(depth=0.6e-3, waves=[(25e-6, 1.0e-3, 0.0, 0.3), (25e-6, 1.0e-3, math.pi / 2, 1.1)])
    eye = torch.eye(4, dtype=torch.float64)
    for surf, repeats in ((lattice, True), (textured(0), False), (textured(3), False)):
        fr = frames(surf, [eye])
        sim = self_similarity(curvature_features(fr.curvature[0], fr.contact[0], 0.7))
        assert (sim is not None) == repeats
        if repeats:
            angle = math.degrees(math.atan2(sim.M[1, 0], sim.M[0, 0]))
            assert min(abs(angle - a) for a in (-180, -90, 0, 90, 180)) < 1.0
            assert abs(math.hypot(sim.M[0, 0], sim.M[1, 0]) - 1.0) < 0.01


def test_self_similarity_refuses_bad_features():
    xy, desc = torch.rand(12, 2) * 100, torch.rand(12, 128)
    with pytest.raises(MatchingError, match="NaN"):
        self_similarity(Features(xy, torch.cat([desc[:11], torch.full((1, 128), math.nan)])))
    with pytest.raises(MatchingError, match="NaN"):
        self_similarity(Features(torch.cat([xy[:11], torch.tensor([[math.inf, 0.0]])]), desc))
    with pytest.raises(MatchingError, match="keypoints"):
        self_similarity(Features(xy[:10], desc))
    with pytest.raises(MatchingError, match="keypoints"):
        self_similarity(Features(xy[:, :1], desc))
    assert self_similarity(Features(torch.zeros(0, 2), torch.zeros(0, 128))) is None  # no keypoints


def test_exceptions():
    with pytest.raises(MatchingError):
        match_descriptors(np.zeros((3, 128)), np.zeros((3, 64)))
    with pytest.raises(MatchingError, match="NaN"):
        match_descriptors(np.full((3, 128), np.nan), np.zeros((3, 128)))
    with pytest.raises(MatchingError):
        estimate_similarity(np.zeros((10, 2)), np.zeros((9, 2)))
    with pytest.raises(MatchingError):
        similarity_to_se3(np.zeros((2, 3)), SHAPE, S)
    with pytest.raises(MatchingError):
        similarity_to_se3(np.zeros((3, 3)), SHAPE, S)
