"""The main job (`make demo` = `tactile-slam demo`) on a short scan: it runs end to end,
writes what the README lists and scores the run against the simulator's ground truth."""

import json

import numpy as np

from tactile_slam.cli.main import main


def test_demo_writes_outputs_and_scores_against_ground_truth(tmp_path, capsys):
    assert main(["demo", "--out", str(tmp_path), "--frames", "80"]) == 0
    for rel in ("episode/gelsight.avi", "episode/gt_poses.npy", "run/poses.npy", "run/stats.json", "run/loops.json",
                "run/metrics.json", "run/report.png", "geometry", "summary.json"):
        assert (tmp_path / rel).exists(), rel
    summary = json.loads((tmp_path / "summary.json").read_text())
    stats, mae = summary["slam"]["stats"], summary["slam"]["per_axis_mae"]
    assert stats["frames"] == 80 and 0 < stats["frames_with_pose"] <= stats["contact_frames"]
    assert stats["loops_pending"] >= 0 and stats["groups"] >= 1
    # image level through the shipped models: sub-millimetre, few-degree tracking
    assert all(np.isfinite(mae[k]) for k in ("x_mm", "y_mm", "z_mm", "rx_deg", "ry_deg", "rz_deg"))
    assert max(mae["x_mm"], mae["y_mm"], mae["z_mm"]) < 0.5 and max(mae["rx_deg"], mae["ry_deg"], mae["rz_deg"]) < 8
    poses = np.load(tmp_path / "run" / "poses.npy")
    assert poses.shape == (80, 4, 4) and np.isnan(poses).any(axis=(1, 2)).sum() == 80 - stats["frames_with_pose"]
    assert "verified but waiting" in capsys.readouterr().out
