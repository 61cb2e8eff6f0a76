"""bench reconstruction: the keyframes and poses of each variant, and a tiny end-to-end run."""

import argparse
import json
import math

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from tactile_slam.bench import reconstruction
from tactile_slam.config import Config, ConfigError
from tactile_slam.geometry.frame import FrameBuilder
from tactile_slam.tracking.keyframe import Keyframe


def keyframe(kf_id: int, video_index: int) -> Keyframe:
    cfg = Config()
    frame = FrameBuilder(cfg).from_gradients(torch.zeros(1, *cfg.sensor.shape, 2),
                                             index=torch.tensor([video_index]))
    return Keyframe(id=kf_id, session=kf_id, maps=frame, new_session=True, prev_T_kf=torch.eye(4, dtype=torch.float64))


def tiny_args(tmp_path) -> argparse.Namespace:
    """A 160-frame dice scan with few samples and touches."""
    p = argparse.ArgumentParser()
    p.add_argument("--out", default=str(tmp_path / "reconstruction.json"))
    reconstruction.add_arguments(p)
    return p.parse_args(["--objects", "dice", "--sizes", "small", "--frames", "160", "--samples", "2000",
                         "--touches", "4", "--work", str(tmp_path / "work")])


def random_poses(n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    out = np.tile(np.eye(4), (n, 1, 1))
    out[:, :3, :3] = Rotation.from_rotvec(rng.normal(0, 1, (n, 3))).as_matrix()
    out[:, :3, 3] = rng.normal(0, 0.01, (n, 3))
    return out


def test_variants_place_each_keyframe_at_its_ground_truth():
    gt = random_poses(50, 0)  # object_T_sensor per video frame
    kfs = [keyframe(i, v) for i, v in enumerate([3, 7, 12, 20, 31, 44])]
    groups = {0: 5, 1: 9, 2: 9, 3: 5, 4: 9, 5: 2}  # group 9 is the largest
    joinable = {0: 1, 1: 1, 2: 0, 3: 1, 4: 0, 5: 1}  # an ideal loop closure's largest group: label 1
    # estimates: group 9 in the frame of an arbitrary start pose, with a small error on keyframe 4
    start = random_poses(1, 1)[0]
    est = {k.id: torch.from_numpy(np.linalg.inv(start) @ gt[k.video_index]) for k in kfs}
    err = np.eye(4)
    err[0, 3] = 1e-4
    est[4] = est[4] @ torch.from_numpy(err)
    for variant in reconstruction.VARIANTS:
        sel, poses, object_T_start = reconstruction.variant_input(variant, kfs, est, groups, gt, joinable)
        ids = [k.id for k in sel]
        assert ids == {"gt_all": [0, 1, 2, 3, 4, 5], "gt_joinable": [0, 1, 3, 5]}.get(variant, [1, 2, 4])
        placed = object_T_start @ poses.numpy()
        expected = gt[[k.video_index for k in sel]]
        if variant == "estimated":  # anchored at the group's first keyframe, the error stays
            np.testing.assert_allclose(placed[:2], expected[:2], atol=1e-12)
            assert abs(np.linalg.norm(placed[2, :3, 3] - expected[2, :3, 3]) - 1e-4) < 1e-9
        else:
            np.testing.assert_allclose(placed, expected, atol=1e-12)
            np.testing.assert_allclose(poses[0].numpy(), np.eye(4), atol=1e-12)
    with pytest.raises(ValueError, match="joinable"):
        reconstruction.variant_input("gt_joinable", kfs, est, groups, gt)


def test_tiny_run_scores_ground_truth_and_estimated_meshes(tmp_path):
    p = argparse.ArgumentParser()
    p.add_argument("--out", default=str(tmp_path / "reconstruction.json"))
    reconstruction.add_arguments(p)
    args = p.parse_args(["--objects", "dice", "--sizes", "small", "--frames", "160", "--samples", "5000",
                         "--touches", "8", "--work", str(tmp_path / "work")])
    doc = json.loads(reconstruction.run(args).read_text())
    runs = doc["results"]["runs"]
    assert [r["variant"] for r in runs] == list(reconstruction.VARIANTS)
    by = {r["variant"]: r for r in runs}
    assert by["gt_all"]["keyframes"] >= by["gt_group"]["keyframes"] == by["estimated"]["keyframes"] >= 2
    system = runs[0]["system"]  # the run's groups and the groups an ideal loop closure could form
    assert system["largest_group"] == by["estimated"]["keyframes"]
    assert system["joinable_largest"] == by["gt_joinable"]["keyframes"] <= by["gt_all"]["keyframes"]
    assert 1 <= system["joinable_groups"] <= system["sessions"]
    funnel = list(system["revisit_funnel"].values())  # each stage counted among the pairs
    assert len(funnel) == 7 and all(0 <= c <= funnel[0] for c in funnel)
    assert funnel[4] >= funnel[5] >= funnel[6]  # matched >= verified >= correct
    loops = json.loads((tmp_path / "work" / "dice_small" / "run" / "loops.json").read_text())
    precision = system["loop_precision"]  # every accepted loop scored against the truth
    assert precision["reported"] == len(loops) and 0 <= precision["correct"] <= len(loops)
    held = json.loads((tmp_path / "work" / "dice_small" / "run" / "loops_held.json").read_text())
    assert sum(m["reported"] for m in system["held_loops"].values()) == len(held)
    assert all(0 <= m["correct"] <= m["reported"] for m in system["held_loops"].values())
    for r in runs:
        for m in (r["mesh"]["gt_pose"], r["mesh"]["icp"], r["fused"]["gt_pose"]):
            assert all(math.isfinite(m[k]) for k in ("chamfer_mm", "recon_to_gt_mm", "gt_to_recon_mm"))
            assert set(m["fscore"]) >= {"0.1", "0.25", "0.5"}
        assert math.isfinite(r["mesh"]["gt_pose"]["ncd"]) and math.isfinite(r["mesh"]["icp"]["ncd"])
        assert r["stats"]["meshing_s"] > 0 and r["stats"]["fusion_s"] > 0
    # where the fused surface exists it lies on the object: to within the gel's smoothing
    # with ground-truth poses, and with the estimated poses of the tracked group too
    # (the watertight Poisson mesh of a partial scan also closes what was never touched)
    assert by["gt_group"]["fused"]["gt_pose"]["recon_to_gt_mm"] < 0.02
    assert by["estimated"]["fused"]["gt_pose"]["recon_to_gt_mm"] < 0.05


def test_a_variant_that_cannot_be_meshed_is_recorded_and_the_rest_go_on(tmp_path, monkeypatch):
    """A group too small to fuse (ReconError) becomes a ``skipped`` entry; the other
    variants are still scored and written."""
    real = reconstruction.reconstruct

    def refuse_estimated(kfs, poses, config):
        if len(kfs) and refuse_estimated.calls == 1:
            refuse_estimated.calls += 1
            raise reconstruction.ReconError("group 0 has no coverage keyframe: too small to fuse")
        refuse_estimated.calls += 1
        return real(kfs, poses, config)

    refuse_estimated.calls = 0
    monkeypatch.setattr(reconstruction, "reconstruct", refuse_estimated)
    args = tiny_args(tmp_path)
    runs = json.loads(reconstruction.run(args).read_text())["results"]["runs"]
    assert [r["variant"] for r in runs] == list(reconstruction.VARIANTS)
    assert "too small to fuse" in runs[1]["skipped"] and "mesh" not in runs[1]
    assert "skipped" not in runs[0] and "skipped" not in runs[2] and "mesh" in runs[2]


def test_variants_scored_before_a_crash_are_already_written(tmp_path, monkeypatch):
    """The JSON is rewritten after every variant: when a later variant dies (here an
    unexpected error in the third), the scored ones are on disk."""
    real = reconstruction.reconstruct

    def die_third(kfs, poses, config):
        die_third.calls += 1
        if die_third.calls == 3:
            raise RuntimeError("meshing crashed")
        return real(kfs, poses, config)

    die_third.calls = 0
    monkeypatch.setattr(reconstruction, "reconstruct", die_third)
    args = tiny_args(tmp_path)
    with pytest.raises(RuntimeError, match="meshing crashed"):
        reconstruction.run(args)
    runs = json.loads((tmp_path / "reconstruction.json").read_text())["results"]["runs"]
    assert [r["variant"] for r in runs] == list(reconstruction.VARIANTS)[:2]
    assert all(math.isfinite(r["mesh"]["gt_pose"]["chamfer_mm"]) for r in runs)


def test_config_file_reaches_the_system_runs(tmp_path, monkeypatch):
    """``--config`` (a YAML of our layout) is the configuration every object run gets; the
    bench's own ``--partial`` still decides the mesh."""
    seen = []

    def capture(name, size_label, args, config, work):
        seen.append(config)
        yield from ()

    monkeypatch.setattr(reconstruction, "object_run", capture)
    cfg = tmp_path / "probes.yaml"
    cfg.write_text("loop:\n  probes: 3\n")
    args = tiny_args(tmp_path)
    args.config = str(cfg)
    reconstruction.run(args)
    assert len(seen) == 1 and seen[0].loop.probes == 3 and seen[0].recon.watertight is True
    args.config = str(tmp_path / "missing.yaml")
    with pytest.raises(ConfigError, match="config file not found"):
        reconstruction.run(args)
