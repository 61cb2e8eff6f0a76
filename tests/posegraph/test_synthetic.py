"""Synthetic scans: ground truth consistency, session split, replay order, bad arguments."""

from __future__ import annotations

import pytest
import torch

from tactile_slam.posegraph import se3
from tactile_slam.posegraph.synthetic import replay_steps, sphere_walk, synthetic_scan


def test_noise_free_measurements_match_ground_truth():
    s = synthetic_scan(40, 20, n_sessions=2, seed=4, radius_m=0.004,
                       odometry_sigma=(0.0, 0.0), loop_sigma=(0.0, 0.0))
    e = s.graph.edges
    gt_rel = se3.inverse(s.gt[e.i]) @ s.gt[e.j]
    assert torch.allclose(e.Z, gt_rel, atol=1e-12)
    assert torch.allclose(s.gt[0], torch.eye(4, dtype=torch.float64))
    assert s.graph.priors.rows.tolist() == [0, 20]
    cross = s.session[s.loops[:, 0]] != s.session[s.loops[:, 1]]
    assert int(e.loop.sum()) == int((~cross).sum())  # loops between sessions are left out
    assert (s.loops[:, 1] - s.loops[:, 0] > 1).all()


def test_walk_stays_on_sphere_and_looks_inward():
    T = sphere_walk(50, radius_m=0.01, seed=1)
    p = T[:, :3, 3]
    assert torch.allclose(p.norm(dim=1), torch.full((50,), 0.01, dtype=torch.float64))
    assert torch.allclose(T[:, :3, 2], -p / 0.01, atol=1e-12)  # z-axis into the object
    steps = (p[1:] - p[:-1]).norm(dim=1)
    assert steps.max() < 1.1e-3


def test_replay_steps_cover_every_factor():
    s = synthetic_scan(30, 15, seed=2, radius_m=0.004)
    steps = replay_steps(s)
    assert [st.t for st in steps] == list(range(30))
    assert steps[0].odometry is None and all(st.odometry is not None for st in steps[1:])
    assert sum(len(st.loops) for st in steps) == int(s.graph.edges.loop.sum())
    assert all(r < st.t for st in steps for r, _ in st.loops)


def test_bad_arguments():
    with pytest.raises(ValueError, match="loop candidates"):
        synthetic_scan(20, 10_000, radius_m=0.004)
    with pytest.raises(ValueError, match="n_keyframes"):
        synthetic_scan(3, 0, n_sessions=5)
