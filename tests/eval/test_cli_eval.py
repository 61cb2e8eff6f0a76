import json

import numpy as np
import pytest

from tactile_slam.cli.eval import SourceMismatchWarning, held_loop_report
from tactile_slam.cli.main import main
from tactile_slam.eval.trajectory import TrajectoryError, relative_to
from tactile_slam.sim.episode import SimulationSettings, simulate_episode


@pytest.fixture(scope="module")
def episode(tmp_path_factory):
    out = tmp_path_factory.mktemp("ep")
    simulate_episode(out, SimulationSettings(object="seed", kind="tracking", frames=30, seed=0))
    return out


def test_eval_cli_writes_metrics_and_plot(episode, tmp_path):
    gt = np.load(episode / "gt_poses.npy")
    est = relative_to(gt, 10)
    est[:10] = np.nan  # background window: no pose
    est[11:, 1, 3] += 0.0002  # 0.2 mm error in y from frame 11 on
    est[20] = np.nan
    run = tmp_path / "run"
    run.mkdir()
    np.save(run / "poses.npy", est)
    assert main(["eval", str(run), "--gt", str(episode)]) == 0
    m = json.loads((run / "metrics.json").read_text())
    t = m["tracking"]
    assert m["reference_frame"] == 10 and m["object"] == "seed" and m["kind"] == "tracking"
    assert t["per_axis_mae"]["y_mm"] == pytest.approx(0.2) and t["per_axis_mae"]["x_mm"] == pytest.approx(0.0)
    assert t["per_axis_mae"]["n_frames"] == 18  # frames 11..29 minus frame 20
    assert t["estimated_fraction"] == pytest.approx(19 / 20)
    assert (run / "tracking_error.png").stat().st_size > 1000


def test_eval_cli_errors(episode, tmp_path):
    assert main(["eval", str(tmp_path), "--gt", str(episode)]) == 2  # no poses.npy
    np.save(tmp_path / "poses.npy", np.tile(np.eye(4), (5, 1, 1)))
    assert main(["eval", str(tmp_path), "--gt", str(episode)]) == 2  # wrong length


def test_eval_cli_scores_reconstruction_in_reference_frame(episode, tmp_path):
    import open3d as o3d

    gt = np.load(episode / "gt_poses.npy")
    est = relative_to(gt, 10)
    est[:10] = np.nan
    np.save(tmp_path / "poses.npy", est)
    mesh = o3d.io.read_triangle_mesh(str(episode / "object.ply"))
    mesh.transform(np.linalg.inv(gt[10]))  # the object in the reference sensor frame
    o3d.io.write_triangle_mesh(str(tmp_path / "mesh.ply"), mesh)
    assert main(["eval", str(tmp_path), "--gt", str(episode), "--touches", "4", "--samples", "20000"]) == 0
    rec = json.loads((tmp_path / "metrics.json").read_text())["reconstruction"]
    assert list(rec) == ["mesh.ply"]
    assert rec["mesh.ply"]["gt_pose"]["chamfer_mm"] < 1e-3
    assert rec["mesh.ply"]["gt_pose"]["ncd"] == pytest.approx(1.0, abs=1e-5)
    assert rec["mesh.ply"]["icp"]["chamfer_mm"] < 1e-3


def test_eval_cli_scores_loops_from_video_within_their_declared_tilt(episode, tmp_path, capsys):
    """Two loops 3 deg off in tilt: the one that declares tilt_sigma_deg 5.44 (from video)
    is correct, the one that declares nothing is not; the full-pose count says neither."""
    from scipy.spatial.transform import Rotation

    gt = np.load(episode / "gt_poses.npy")
    est = relative_to(gt, 10)
    est[:10] = np.nan
    np.save(tmp_path / "poses.npy", est)
    (tmp_path / "keyframes.json").write_text(json.dumps([{"id": 0, "video_index": 12}, {"id": 1, "video_index": 25}]))
    rel = np.linalg.inv(gt[12]) @ gt[25]
    rel[:3, :3] = rel[:3, :3] @ Rotation.from_rotvec([np.deg2rad(3.0), 0, 0]).as_matrix()
    loops = [{"ref_id": 0, "tar_id": 1, "ref_T_tar": rel.tolist(), "tilt_sigma_deg": sigma} for sigma in (5.44, None)]
    (tmp_path / "loops.json").write_text(json.dumps(loops))
    assert main(["eval", str(tmp_path), "--gt", str(episode), "--no-recon"]) == 0
    m = json.loads((tmp_path / "metrics.json").read_text())["loops"]
    assert (m["reported"], m["correct"], m["correct_full_pose"]) == (2, 1, 0)
    assert "loops: 1 of 2 correct (0 within 1 deg in full pose" in capsys.readouterr().out


def _held_run(tmp_path, held) -> tuple:
    """A run folder with two keyframes (video frames 3 and 7) and ``loops_held.json``."""
    run = tmp_path / "run"
    run.mkdir()
    (run / "keyframes.json").write_text(json.dumps([{"id": 0, "video_index": 3}, {"id": 1, "video_index": 7}]))
    (run / "loops_held.json").write_text(held if isinstance(held, str) else json.dumps(held))
    gt = np.repeat(np.eye(4)[None], 10, axis=0)
    gt[7, 0, 3] = 0.001  # keyframe 1 is 1 mm along x of keyframe 0
    return run, gt


def test_held_loop_report_scores_each_reason(tmp_path):
    right, off = np.eye(4), np.eye(4)
    right[0, 3], off[0, 3] = 0.001, 0.0015  # the truth, and 0.5 mm off
    held = [{"ref_id": 0, "tar_id": 1, "ref_T_tar": right.tolist(), "reason": "waiting"},
            {"ref_id": 0, "tar_id": 1, "ref_T_tar": off.tolist(), "reason": "waiting"},
            {"ref_id": 0, "tar_id": 1, "ref_T_tar": off.tolist(), "reason": "repetitive"}]
    run, gt = _held_run(tmp_path, held)
    report = held_loop_report(run, gt)
    assert {r: (m["correct"], m["reported"]) for r, m in report.items()} == {"repetitive": (0, 1), "waiting": (1, 2)}
    assert report["repetitive"]["trans_err_mm"] == pytest.approx(0.5)


@pytest.mark.parametrize("held, match", [
    ("{not json", "cannot read"),
    ({"ref_id": 0}, "not a list of loop records"),
    ([{"ref_id": 0, "tar_id": 1, "ref_T_tar": np.eye(4).tolist()}], "reason"),  # no reason
    ([{"ref_id": 0, "tar_id": 9, "ref_T_tar": np.eye(4).tolist(), "reason": "waiting"}], r"keyframes \[9\]"),
    ([{"ref_id": 0, "tar_id": 1, "ref_T_tar": np.eye(4).tolist(), "reason": "waiting", "tilt_sigma_deg": "x"}],
     "tilt_sigma_deg"),
    ([{"ref_id": 0, "tar_id": 1, "ref_T_tar": np.eye(4).tolist(), "reason": "waiting", "tilt_sigma_deg": -1}],
     "tilt_sigma_deg"),
])
def test_held_loop_report_refuses_malformed_files(tmp_path, held, match):
    run, gt = _held_run(tmp_path, held)
    with pytest.raises(TrajectoryError, match=match):
        held_loop_report(run, gt)


def test_held_loop_report_of_no_held_loops_is_empty(tmp_path):
    run, gt = _held_run(tmp_path, [])
    assert held_loop_report(run, gt) == {}


def _run_of(episode, run):
    """A run folder with the episode's exact poses from frame 10 on."""
    est = relative_to(np.load(episode / "gt_poses.npy"), 10)
    est[:10] = np.nan
    run.mkdir()
    np.save(run / "poses.npy", est)
    return run


def test_eval_warns_when_the_run_read_another_episode(episode, tmp_path, monkeypatch):
    """eval scored a run against any episode of the same length; the run's stats.json
    now names its source, and one outside the episode folder is warned of (and scored)."""
    import warnings

    run = _run_of(episode, tmp_path / "run")
    other = f"{episode}_other/gt_gradients.npz"  # a sibling whose name starts like the episode's
    (run / "stats.json").write_text(json.dumps({"source": other}))
    with pytest.warns(SourceMismatchWarning) as record:
        assert main(["eval", str(run), "--gt", str(episode), "--no-recon"]) == 0
    assert other in str(record[0].message) and str(episode.resolve()) in str(record[0].message)
    assert (run / "metrics.json").is_file()
    (run / "stats.json").write_text(json.dumps({"source": "camera 0"}))  # not a path: never the episode,
    monkeypatch.chdir(episode)  # even where it would resolve inside the episode folder
    with pytest.warns(SourceMismatchWarning):
        assert main(["eval", str(run), "--gt", ".", "--no-recon"]) == 0
    for stats in ({"source": str(episode / "gt_gradients.npz")}, {"source": str(episode)}, {"frames": 30}):
        (run / "stats.json").write_text(json.dumps(stats))
        with warnings.catch_warnings():
            warnings.simplefilter("error", SourceMismatchWarning)
            assert main(["eval", str(run), "--gt", str(episode), "--no-recon"]) == 0
    (run / "stats.json").write_text("{broken")
    assert main(["eval", str(run), "--gt", str(episode), "--no-recon"]) == 2


def _reflect(p):
    p[:3, 0] *= -1


def _bottom_row(p):
    p[3] = [1, 2, 3, 4]


def _shear(p):
    p[0, 1] += 0.01


@pytest.mark.parametrize("spoil, message", [(_reflect, "determinant -1"), (_bottom_row, "bottom row"),
                                            (_shear, "not orthonormal")])
def test_eval_names_file_and_video_frame_of_a_non_rigid_pose(episode, tmp_path, capsys, spoil, message):
    """A reflection gave scipy's "Non-positive determinant ... matrix 5" (5 counted among
    the frames with a pose) and a bottom row [1, 2, 3, 4] was scored."""
    run = _run_of(episode, tmp_path / "run")
    est = np.load(run / "poses.npy")
    spoil(est[15])
    np.save(run / "poses.npy", est)
    assert main(["eval", str(run), "--gt", str(episode), "--no-recon"]) == 2
    err = capsys.readouterr().err
    assert f"{run / 'poses.npy'}: frame 15 is not a rigid pose" in err and message in err


def test_eval_names_an_unreadable_pose_file(episode, tmp_path, capsys):
    run = tmp_path / "run"
    run.mkdir()
    (run / "poses.npy").write_text("garbage")
    assert main(["eval", str(run), "--gt", str(episode), "--no-recon"]) == 2
    err = capsys.readouterr().err
    assert f"{run / 'poses.npy'} is not a NumPy .npy file" in err and "pickled" not in err
    np.save(run / "poses.npy", np.array([{"a": 1}], dtype=object), allow_pickle=True)
    assert main(["eval", str(run), "--gt", str(episode), "--no-recon"]) == 2
    assert f"cannot read {run / 'poses.npy'}: Object arrays" in capsys.readouterr().err
