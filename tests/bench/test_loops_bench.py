"""bench loops, back-end section: tracked keyframes through the back end, scored on the truth."""

import json

import torch

from tactile_slam.bench import loops
from tactile_slam.cli.main import main
from tactile_slam.config import Config
from tactile_slam.posegraph import se3


def test_tracked_keyframes_carry_real_odometry():
    config = Config()
    kfs, obj_T = loops.tracked_keyframes("seed", "tracking", 90, 0, config)
    assert len(kfs) >= 3 and obj_T.shape == (90, 4, 4)
    assert [k.id for k in kfs] == list(range(len(kfs)))
    T = torch.as_tensor(obj_T, dtype=torch.float64)
    for prev, kf in zip(kfs, kfs[1:]):
        if kf.session == prev.session:  # odometry of the tracker, close to the truth on the seed
            true = se3.inverse(T[prev.video_index]) @ T[kf.video_index]
            assert float((kf.prev_T_kf[:3, 3] - true[:3, 3]).norm()) < 2e-4
        assert kf.frame.gradients is None and len(kf.frame) == 1 and kf.frame.normals.is_contiguous()


def test_backend_section_scores_gate_and_no_gate(tmp_path):
    out = tmp_path / "loops.json"
    cfg = tmp_path / "edge.yaml"
    cfg.write_text("loop:\n  sift_edge_threshold: 12.5\n")
    threads = torch.get_num_threads()
    try:
        assert main(["bench", "loops", "--out", str(out), "--objects", "--sizes", "--index-sizes",
                     "--backend-objects", "seed", "--backend-kinds", "tracking", "--frames", "160",
                     "--threads", "1", "--config", str(cfg)]) == 0
    finally:
        torch.set_num_threads(threads)
    doc = json.loads(out.read_text())
    assert doc["machine"]["torch_threads"] == 1  # as the online back end runs it
    assert doc["results"]["config"]["loop"]["sift_edge_threshold"] == 12.5  # the runs' configuration
    res = doc["results"]["backend"]
    assert set(res) == {"seed/tracking/gate", "seed/tracking/no_gate"}
    for r in res.values():
        assert r["accepted"] == r["correct"] + r["false"] and r["false"] == 0
        assert r["accepted"] >= 1 and 0 < r["query_recall"] <= 1
    gate = res["seed/tracking/gate"]["summary"]["loop_gate"]
    assert gate is not None and res["seed/tracking/no_gate"]["summary"]["loop_gate"] is None


def test_wrong_loop_judges_against_the_release_gate():
    from tactile_slam.backend import BackEnd
    from tests.loop.revisit import revisit_keyframes

    kfs, kf0_T = revisit_keyframes()
    be = BackEnd(Config())
    for k in kfs:
        be.add(k)
    (lp,) = be.loops
    kmap = {k.id: k for k in kfs}
    assert loops.wrong_loop(lp, kf0_T, kmap) is None
    # the truth of keyframe 2 turned by 2 deg about the sensor axis: the same loop is now wrong by 2 deg
    c, s = torch.cos(torch.tensor(2.0).deg2rad()), torch.sin(torch.tensor(2.0).deg2rad())
    turn = torch.eye(4, dtype=torch.float64)
    turn[:2, :2] = torch.tensor([[c, -s], [s, c]], dtype=torch.float64)
    moved = kf0_T.clone()
    moved[2] = kf0_T[2] @ turn
    record = loops.wrong_loop(lp, moved, kmap)
    true_rot, _ = loops.loop_error(lp, se3.inverse(kf0_T[0]) @ kf0_T[2], kmap)
    assert record["ref"] == 0 and record["tar"] == 2 and abs(record["rot_deg"] - 2.0) <= true_rot + 1e-6
    assert set(record) == {"ref", "tar", "rot_deg", "trans_mm", "ccs", "scr", "inliers"}
