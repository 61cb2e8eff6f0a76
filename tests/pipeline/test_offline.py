"""End-to-end runs of the offline pipeline on short simulated episodes (gradient level)."""

from __future__ import annotations

import argparse
import json

import cv2
import numpy as np
import open3d as o3d
import pytest
import torch

from tactile_slam.cli.devices import device_arg
from tactile_slam.cli.main import main
from tactile_slam.config import Config
from tactile_slam.eval.tracking_metrics import per_axis_mae
from tactile_slam.geometry.frame import CroppedFrame, InputError
from tactile_slam.io.gradients import GradientSequence
from tactile_slam.pipeline.offline import OfflinePipeline, RunOptions
from tactile_slam.sim.episode import SimulationSettings, read_episode, simulate_episode
from tactile_slam.tracking.frame_to_frame import FrameToFrameTracker

STATS_KEYS = {"frames", "contact_frames", "keyframes", "sessions", "fps", "timing_ms", "frames_with_pose",
              "implausible_motions", "moved_keyframe_edges", "kept_keyframe_edges", "coarse_rescues",
              "registration_breaks"}


@pytest.fixture(scope="module")
def tracking_episode(tmp_path_factory):
    out = tmp_path_factory.mktemp("ep_tracking")
    return simulate_episode(out, SimulationSettings(object="seed", kind="tracking", frames=60, seed=3))


@pytest.fixture(scope="module")
def contact_loss_episode(tmp_path_factory):
    # long enough for two sessions to meet twice: groups merge only on two agreeing loops
    # from distinct keyframes on both sides (docs/loops.md)
    out = tmp_path_factory.mktemp("ep_loss")
    return simulate_episode(out, SimulationSettings(object="seed", kind="contact_loss", frames=400, seed=4))


def gt_relative(episode_dir, first):
    ep = read_episode(episode_dir)
    gt = ep.object_T_sensor
    rel = np.linalg.inv(gt[first]) @ gt
    return rel, ep.in_contact


def run(episode_dir, out, method, mesh=False):
    src = GradientSequence(episode_dir / "gt_gradients.npz", fps=25)
    return OfflinePipeline(src, Config(), out, RunOptions(method=method, progress=False, mesh=mesh)).run()


def check_frames_csv(out, res, config=Config(), fps=25.0):
    """``frames.csv`` against the run's other outputs: one row per video frame; the group of
    ``frame_group.npy``; the keyframes and sessions of ``keyframes.json``; scores exactly
    where a frame was registered (not a session head, in contact), and those passing the
    tracking thresholds, since they are the accepted registrations'."""
    table = np.genfromtxt(out / "frames.csv", delimiter=",", names=True)
    t = len(res.poses)
    assert table.dtype.names == ("index", "time_s", "group", "session", "keyframe_id", "is_keyframe",
                                 "ccs", "scr", "conditioning")
    assert len(table) == t
    np.testing.assert_array_equal(table["index"], np.arange(t))
    np.testing.assert_allclose(table["time_s"], np.arange(t) / fps, atol=1e-6)
    np.testing.assert_array_equal(table["group"], res.frame_group)
    kfs = json.loads((out / "keyframes.json").read_text())
    np.testing.assert_array_equal(np.flatnonzero(table["is_keyframe"]), sorted(k["video_index"] for k in kfs))
    session = {k["id"]: k["session"] for k in kfs}
    tracked = res.frame_group >= 0
    np.testing.assert_array_equal(table["keyframe_id"] >= 0, tracked)
    assert all(table["session"][i] == session[int(table["keyframe_id"][i])] for i in np.flatnonzero(tracked))
    assert (table["session"][~tracked] == -1).all()
    heads = {k["video_index"] for k in kfs if k["new_session"]}
    scored = tracked & ~np.isin(np.arange(t), list(heads))
    for name in ("ccs", "scr", "conditioning"):
        np.testing.assert_array_equal(np.isfinite(table[name]), scored)
    tc = config.tracking
    assert (table["ccs"][scored] >= tc.ccs_threshold).all() and (table["scr"][scored] >= tc.scr_threshold).all()
    assert ((table["conditioning"][scored] > 0) & (table["conditioning"][scored] <= 1)).all()


@pytest.mark.parametrize("method", ["nf-kf", "gelslam"])
def test_tracking_episode_accuracy(tracking_episode, tmp_path, method):
    res = run(tracking_episode, tmp_path, method, mesh=method == "gelslam")
    first = int(np.nonzero(res.frame_group >= 0)[0][0])
    gt, in_contact = gt_relative(tracking_episode, first)
    assert res.poses.shape == (len(gt), 4, 4)
    has = np.isfinite(res.poses).all(axis=(1, 2))
    # every in-contact frame has a pose, frames without contact have NaN rows
    np.testing.assert_array_equal(has, res.frame_group >= 0)
    assert has.sum() >= 0.9 * in_contact.sum()
    assert not has[~in_contact].any()
    mae = per_axis_mae(res.poses, gt, has)
    assert max(mae["x_mm"], mae["y_mm"], mae["z_mm"]) < 0.05, mae
    assert max(mae["rx_deg"], mae["ry_deg"], mae["rz_deg"]) < 0.5, mae
    # keyframes are kept around their contact once the back end has them (the mesh below is fused from those)
    assert res.keyframes and all(isinstance(k.maps, CroppedFrame) for k in res.keyframes)
    assert sum(k.maps.box.height.numel() for k in res.keyframes) < len(res.keyframes) * 240 * 320
    stats = json.loads((tmp_path / "stats.json").read_text())
    assert STATS_KEYS <= set(stats) and stats["completed"]
    for name in ("poses.npy", "trajectory_tum.txt", "keyframes.json", "config.yaml"):
        assert (tmp_path / name).is_file()
    check_frames_csv(tmp_path, res)
    tum = np.loadtxt(tmp_path / "trajectory_tum.txt")
    assert len(tum) == has.sum()
    np.testing.assert_allclose(tum[:, 1:4], res.poses[has, :3, 3], atol=1e-9)
    np.testing.assert_allclose(tum[:, 0], np.flatnonzero(has) / 25.0, atol=1e-9)  # t = video index / fps
    if method == "gelslam":
        # the fused surface, brought into the object frame through the ground-truth pose
        # of the first contact frame, lies on the object
        ep = read_episode(tracking_episode)
        fused = o3d.io.read_triangle_mesh(str(tmp_path / "mesh_fused.ply"))
        v = np.asarray(fused.vertices)
        T = ep.object_T_sensor[first]
        v_obj = v @ T[:3, :3].T + T[:3, 3]
        scene = o3d.t.geometry.RaycastingScene()
        scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(ep.mesh()))
        dist = scene.compute_distance(o3d.core.Tensor(v_obj.astype(np.float32))).numpy()
        assert len(v) > 1000 and np.median(dist) < 0.05e-3, np.median(dist)
        assert (tmp_path / "mesh.ply").is_file() and (tmp_path / "mesh.png").is_file()


def test_contact_loss_sessions_merge_with_loops(contact_loss_episode, tmp_path):
    full = run(contact_loss_episode, tmp_path / "full", "gelslam")
    odo = run(contact_loss_episode, tmp_path / "odo", "nf-kf")
    assert full.stats["sessions"] >= 2 and odo.stats["groups"] == odo.stats["sessions"]
    for out, res in ((tmp_path / "odo", odo), (tmp_path / "full", full)):  # sessions, gaps, merged groups
        check_frames_csv(out, res)
    assert full.stats["loops"] >= 1 and full.stats["groups"] < full.stats["sessions"]
    # the largest merged group: its frames are posed in the frame of its first frame
    groups, counts = np.unique(full.frame_group[full.frame_group >= 0], return_counts=True)
    g = groups[np.argmax(counts)]
    sel = full.frame_group == g
    assert counts.max() > np.bincount(odo.frame_group[odo.frame_group >= 0]).max()
    first = int(np.nonzero(sel)[0][0])
    gt, _ = gt_relative(contact_loss_episode, first)
    mae = per_axis_mae(full.poses_by_group, gt, sel)
    assert max(mae["x_mm"], mae["y_mm"], mae["z_mm"]) < 0.1, mae
    assert max(mae["rx_deg"], mae["ry_deg"], mae["rz_deg"]) < 1.0, mae
    loops = json.loads((tmp_path / "full" / "loops.json").read_text())
    assert len(loops) == full.stats["loops"]
    # every verified loop left out of the graph, with the gate's reason, as its counters say
    held = json.loads((tmp_path / "full" / "loops_held.json").read_text())
    reasons = [lp["reason"] for lp in held]
    gate = full.stats["loop_gate"]
    assert set(reasons) <= {"asymmetric", "repetitive", "ambiguous", "inconsistent", "waiting", "doubtful"}
    assert reasons.count("asymmetric") == full.stats["asymmetric_loops"]
    assert reasons.count("waiting") + reasons.count("doubtful") == gate["pending"]
    assert reasons.count("repetitive") + reasons.count("ambiguous") == gate["repetitive"]
    assert reasons.count("inconsistent") == gate["rejected_consistency"]
    assert not {(lp["ref_id"], lp["tar_id"]) for lp in held} & {(lp["ref_id"], lp["tar_id"]) for lp in loops}
    # the paper's statistics: every loop was a candidate, coverage keyframes are keyframes
    assert full.stats["loop_candidates"] >= full.stats["loops"]
    assert 1 <= full.stats["coverage_keyframes"] <= full.stats["keyframes"]
    assert (tmp_path / "full" / "pose_graph.g2o").is_file() and (tmp_path / "full" / "pose_graph.png").is_file()


def test_no_contact_is_an_error_and_writes_nothing(tmp_path):
    np.savez(tmp_path / "flat.npz", gradients=np.zeros((5, 240, 320, 2), np.float16),
             contact=np.zeros((5, 240, 320), bool))
    src = GradientSequence(tmp_path / "flat.npz", fps=25)
    with pytest.raises(InputError, match="no frame of 5 is in contact"):
        OfflinePipeline(src, Config(), tmp_path / "out", RunOptions(progress=False)).run()
    assert not (tmp_path / "out").exists()


def test_a_model_of_another_field_of_view_is_warned_about(tmp_path):
    """An image recording decoded with a model trained on a gel of another size warns,
    naming the model file, before anything is tracked."""
    from tactile_slam.calibration.model import GradientMLP, ModelSensorWarning, save_model
    from tactile_slam.io.video import VideoSource, write_video

    save_model(tmp_path / "other.pt", GradientMLP(), {"image_size": [240, 320], "mm_per_px": 0.05})
    grey = np.full((12, 240, 320, 3), 128, np.uint8)  # no contact: the run stops after the warning
    write_video(tmp_path / "flat.avi", grey, 25.0)
    options = RunOptions(progress=False, model=str(tmp_path / "other.pt"))
    with pytest.warns(ModelSensorWarning, match="other.pt: the model was trained on a 16.00 x 12.00 mm"):
        with pytest.raises(InputError):
            OfflinePipeline(VideoSource(tmp_path / "flat.avi"), Config(), tmp_path / "out", options).run()


def test_greyscale_frames_are_warned_about(tmp_path):
    """The decode reads colour: a greyscale recording (B = G = R) warns before tracking."""
    from tactile_slam.io.scan import BackgroundWarning, is_grey
    from tactile_slam.io.video import VideoSource, write_video

    write_video(tmp_path / "grey.avi", np.full((12, 240, 320, 3), 128, np.uint8), 25.0)
    with pytest.warns(BackgroundWarning, match="greyscale"):
        with pytest.raises(InputError):  # and no contact
            OfflinePipeline(VideoSource(tmp_path / "grey.avi"), Config(), tmp_path / "out",
                            RunOptions(progress=False)).run()
    colour = np.full((4, 4, 3), 128.0)
    colour[1, 2] = (120, 128, 135)
    assert is_grey(np.full((4, 4, 3), 77.0)) and not is_grey(colour)


def test_no_contact_after_a_touched_background_says_why(tmp_path):
    """A video pressed from its first frame: the background window holds the contact, so
    every later frame matches it; the error points at the background, not at the scan."""
    from tactile_slam.io.video import VideoSource, write_video
    from tactile_slam.sim.episode import synthetic_background

    bg = synthetic_background((240, 320)).astype(np.int16)
    pressed = bg.copy()
    pressed[100:140, 140:180] += 40
    frames = [bg] * 3 + [pressed] * 12  # touched at frame 3, inside the 10-frame window
    write_video(tmp_path / "v.avi", np.clip(np.stack(frames), 0, 255).astype(np.uint8), 25.0)
    with pytest.warns(UserWarning, match="was the gel touched"):
        with pytest.raises(InputError, match="taken as the background, differ.*background.png"):
            OfflinePipeline(VideoSource(tmp_path / "v.avi"), Config(), tmp_path / "out",
                            RunOptions(progress=False, mesh=False)).run()


def test_cli_bad_inputs(tmp_path, capsys):
    assert main(["run", str(tmp_path / "missing"), "--out", str(tmp_path / "o1")]) == 2
    assert "not found" in capsys.readouterr().err
    scan = tmp_path / "scan"
    scan.mkdir()
    (scan / "gelsight.avi").write_bytes(b"\x00" * 1000)  # corrupt video
    assert main(["run", str(scan), "--out", str(tmp_path / "o2")]) == 2
    err = capsys.readouterr().err
    assert "gelsight.avi" in err
    assert not (tmp_path / "o2").exists()


def test_cli_frames_of_another_size_need_resize(mini_data, tmp_path, capsys):
    """A 640x480 recording is refused with a message naming --resize, and tracked with it."""
    from tactile_slam.io.video import write_video

    calib = mini_data / "calibration"
    big = [cv2.resize(cv2.imread(str(p)), (640, 480))
           for p in (calib / "background.png", calib / "6.310mm" / "3" / "gelsight.png")]
    scan = tmp_path / "big"
    scan.mkdir()
    write_video(scan / "gelsight.avi", np.stack([big[0]] * 10 + [big[1]] * 4), 25.0)
    assert main(["run", str(scan), "--out", str(tmp_path / "o1"), "--no-mesh"]) == 2
    assert "640x480" in (err := capsys.readouterr().err) and "--resize" in err
    assert not (tmp_path / "o1").exists()
    assert main(["run", str(scan), "--out", str(tmp_path / "o2"), "--no-mesh", "--resize", "--no-progress"]) == 0
    stats = json.loads((tmp_path / "o2" / "stats.json").read_text())
    assert stats["contact_frames"] == 4 and stats["sessions"] == 1


def test_cli_run_says_when_the_object_covered_the_gel(tmp_path, capsys):
    """A sequence whose contact covers the whole gel in its first touched frames: those
    keyframes are flagged in keyframes.json and stats.json, and the run says so."""
    from tests.registration.surfaces import frames, rigid, textured

    views = [rigid(tx_mm=0.05 * i) for i in range(12)]
    f = frames(textured(5), views)
    grads = np.concatenate([np.zeros((3, *f.gradients.shape[1:]), np.float32), f.gradients.numpy()])
    contact = np.concatenate([np.zeros((3, *f.contact.shape[1:]), bool), f.contact.numpy()])
    contact[3:6] = True  # the first three touched frames: gel covered edge to edge
    np.savez(tmp_path / "seq.npz", gradients=grads, contact=contact)
    out = tmp_path / "o"
    assert main(["run", str(tmp_path / "seq.npz"), "--out", str(out), "--no-mesh", "--no-progress",
                 "--method", "nf-kf"]) == 0
    kfs = json.loads((out / "keyframes.json").read_text())
    unknown = [k["video_index"] for k in kfs if not k["depth_known"]]
    assert unknown and set(unknown) <= {3, 4, 5} and kfs[0]["video_index"] == 3
    stats = json.loads((out / "stats.json").read_text())
    assert stats["keyframes_depth_unknown"] == len(unknown)
    assert f"{len(unknown)} keyframes saw no undeformed gel" in capsys.readouterr().out


def test_cli_run_says_when_sessions_break_inside_a_contact(tmp_path, capsys):
    """One long touch of a textureless flat face (zero slopes over a held contact disc):
    NormalFlow's degeneracy test fails every registration, so each frame after the first
    starts a session inside the contact; stats.json counts them and the run says so."""
    h, w = 240, 320
    y, x = np.mgrid[0:h, 0:w]
    disc = (x - w / 2) ** 2 + (y - h / 2) ** 2 < 80 ** 2
    contact = np.zeros((8, h, w), bool)
    contact[2:] = disc
    np.savez(tmp_path / "flat.npz", gradients=np.zeros((8, h, w, 2), np.float32), contact=contact)
    out = tmp_path / "o"
    assert main(["run", str(tmp_path / "flat.npz"), "--out", str(out), "--no-mesh", "--no-progress",
                 "--method", "nf-kf"]) == 0
    stats = json.loads((out / "stats.json").read_text())
    assert stats["sessions"] == 6 and stats["registration_breaks"] == 5  # one touch, five breaks
    assert "5 of the 6 sessions began inside a contact" in capsys.readouterr().out


@pytest.mark.skipif(torch.cuda.is_available(), reason="needs a machine without CUDA")
def test_cli_cuda_without_a_gpu_is_a_clear_error(tmp_path, capsys):
    with pytest.raises(SystemExit) as exc:
        main(["run", str(tmp_path), "--out", str(tmp_path / "o"), "--device", "cuda"])
    assert exc.value.code == 2
    assert "--device: cuda: CUDA is not available" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


def test_device_argument():
    assert device_arg("cpu") == "cpu"
    assert device_arg("auto") == ("cuda" if torch.cuda.is_available() else "cpu")
    for bad in ("", "gpu", "mps", "cuda:99"):
        with pytest.raises(argparse.ArgumentTypeError):
            device_arg(bad)


def test_gradient_input_runs_on_the_requested_device(tracking_episode, tmp_path, device):
    """Gradient sequences are computed where ``RunOptions.device`` says (they never pass
    through a decoder, whose device the image level follows), and stats say so."""
    src = GradientSequence(tracking_episode / "gt_gradients.npz", fps=25)
    res = OfflinePipeline(src, Config(), tmp_path, RunOptions(method="nf-kf", progress=False, mesh=False,
                                                              device=str(device))).run()
    assert res.stats["device"] == device.type and res.keyframes
    assert all(kf.maps.device.type == device.type for kf in res.keyframes)


def test_result_carries_the_keyframe_poses_for_reconstruction(tracking_episode, tmp_path):
    """``RunResult.start_T_kf`` / ``keyframe_group`` are what ``keyframes.json`` and
    ``frame_group.npy`` say, and feed ``reconstruct`` from Python without re-reading files."""
    from tactile_slam.recon import reconstruct

    res = run(tracking_episode, tmp_path, "gelslam")
    stored = {k["id"]: k for k in json.loads((tmp_path / "keyframes.json").read_text())}
    assert set(res.start_T_kf) == set(res.keyframe_group) == set(stored)
    for i, pose in res.start_T_kf.items():
        np.testing.assert_array_equal(pose.numpy(), np.array(stored[i]["pose"]))
    first = {kf.id: kf.video_index for kf in res.keyframes}
    for i, group in res.keyframe_group.items():
        assert res.frame_group[first[i]] == group
    rec = reconstruct(res.keyframes, res.start_T_kf, Config(), res.keyframe_group)
    assert len(rec.fused_mesh.vertices) > 0


def test_a_new_run_replaces_every_output_of_an_earlier_one(tracking_episode, tmp_path):
    """Outputs the new run does not write (loops, graph, meshes, an earlier eval's metrics)
    are removed, so nothing of the earlier run is read as the new one's; other files stay."""
    run(tracking_episode, tmp_path, "gelslam", mesh=True)
    (tmp_path / "metrics.json").write_text("{}")
    (tmp_path / "notes.txt").write_text("mine")
    before = {p.name for p in tmp_path.iterdir()}
    assert {"loops.json", "pose_graph.g2o", "mesh.ply"} <= before
    run(tracking_episode, tmp_path, "nf-kf")
    after = {p.name for p in tmp_path.iterdir()}
    assert not after & {"loops.json", "loops_held.json", "pose_graph.g2o", "pose_graph.png", "mesh.ply",
                        "mesh_fused.ply", "mesh.png", "metrics.json"}
    assert "notes.txt" in after and json.loads((tmp_path / "stats.json").read_text())["method"] == "nf-kf"


def _interrupted_after(source, n):
    """``source``'s frames, then a Ctrl+C after the ``n``-th."""
    for i, frame in enumerate(source):
        if i == n:
            raise KeyboardInterrupt
        yield frame


def test_an_interrupt_keeps_the_frames_before_it(tracking_episode, tmp_path):
    src = GradientSequence(tracking_episode / "gt_gradients.npz", fps=25)
    res = OfflinePipeline(_interrupted_after(src, 30), Config(), tmp_path / "out",
                          RunOptions(method="nf-kf", progress=False, mesh=False, batch_size=8)).run()
    assert not res.stats["completed"] and res.stats["frames"] == 30
    assert res.stats["error"].startswith("KeyboardInterrupt")
    assert np.load(tmp_path / "out" / "poses.npy").shape == (30, 4, 4)
    with pytest.raises(KeyboardInterrupt):  # before the first frame: nothing to keep, nothing written
        OfflinePipeline(_interrupted_after(src, 0), Config(), tmp_path / "none",
                        RunOptions(method="nf-kf", progress=False, mesh=False)).run()
    assert not (tmp_path / "none").exists()


def test_nf_baseline_is_the_public_trackers_normalflow(tmp_path):
    """``nf``: frame-to-frame, 5000 random samples, no CCS/SCR checks and none of this
    package's sample rules (slope limits, spread cells); ``nf-kf`` keeps them."""
    nf = OfflinePipeline(iter([]), Config(), tmp_path, RunOptions(method="nf"))._tracker()
    cfg = nf.registrar.config
    assert isinstance(nf, FrameToFrameTracker)
    assert (cfg.n_samples, cfg.selection, cfg.check_scores, cfg.decoded_max_slope, cfg.max_slope) == (
        5000, "random", False, None, None)
    kf = OfflinePipeline(iter([]), Config(), tmp_path, RunOptions(method="nf-kf"))._tracker()
    assert kf.registrar.config.decoded_max_slope == Config().normalflow.decoded_max_slope == 0.5
    assert kf.registrar.config.max_slope == Config().normalflow.max_slope == 0.5
    assert kf.registrar.config.selection == "spread"


def test_method_validation(tmp_path):
    with pytest.raises(ValueError, match="method must be one of"):
        OfflinePipeline(iter([]), Config(), tmp_path, RunOptions(method="icp"))
    if not torch.cuda.is_available():
        with pytest.raises(ValueError, match="CUDA is not available"):
            OfflinePipeline(iter([]), Config(), tmp_path, RunOptions(device="cuda"))


def test_scan_folder_skips_its_background_frames(tracking_episode, tmp_path):
    """A recorded scan's frames keep their video indices; the 10 contact-free leading
    frames become the background and are not yielded (``poses.npy`` rows of a scan:
    ``tests/pipeline/test_real_presses.py``)."""
    from tactile_slam.io.scan import Scan
    from tactile_slam.io.video import write_video

    grads, contact = read_episode(tracking_episode).gradients()
    # colour stand-in: an image whose change against the background follows the slopes
    bg = np.full((240, 320, 3), 120, np.uint8)
    imgs = [bg] * 10 + [np.clip(bg + 400 * g[..., :1].astype(np.float32) * np.ones(3), 0, 255).astype(np.uint8)
                        for g in grads[:5]]
    scan = tmp_path / "scan"
    scan.mkdir()
    write_video(scan / "gelsight.avi", np.stack(imgs), 25)
    s = Scan(scan)
    assert s.start == 10 and len(s) == 5
    assert [f.index for f in s] == list(range(10, 15))


def test_no_mesh_computes_no_reconstruction_and_gradients_need_no_model(tracking_episode, tmp_path):
    """``--no-mesh`` (``RunOptions.mesh=False``) writes no mesh files and no reconstruction
    statistics; gradient-level input never loads the calibration model, so a missing
    model file does not matter."""
    cfg = Config()
    cfg.sensor.model_path = str(tmp_path / "no_such_model.pt")
    src = GradientSequence(tracking_episode / "gt_gradients.npz", fps=25)
    res = OfflinePipeline(src, cfg, tmp_path / "out", RunOptions(method="gelslam", progress=False, mesh=False)).run()
    assert res.stats["completed"] and res.stats["keyframes"] > 0
    written = {p.name for p in (tmp_path / "out").iterdir()}
    assert {"poses.npy", "stats.json", "loops.json"} <= written
    assert not written & {"mesh_fused.ply", "mesh.ply", "mesh.png"}
    assert "reconstruction" not in res.stats


def test_eval_scores_accepted_loops(contact_loss_episode, tmp_path, capsys):
    """`tactile-slam eval` reports the precision of the run's loops against ground truth,
    and of the verified loops the back end held out of the graph, per reason."""
    run(contact_loss_episode, tmp_path, "gelslam")
    assert main(["eval", str(tmp_path), "--gt", str(contact_loss_episode), "--no-recon"]) == 0
    metrics = json.loads((tmp_path / "metrics.json").read_text())
    loops = metrics["loops"]
    assert loops["reported"] >= 1 and loops["precision"] == 1.0
    assert loops["trans_err_mm"] < 0.3 and loops["rot_err_deg"] < 1.0
    assert f"loops: {loops['correct']} of {loops['reported']} correct" in capsys.readouterr().out
    held = json.loads((tmp_path / "loops_held.json").read_text())
    by_reason = metrics["held_loops"]
    assert sum(m["reported"] for m in by_reason.values()) == len(held)
    assert {r: m["reported"] for r, m in by_reason.items()} == {r: [lp["reason"] for lp in held].count(r)
                                                                 for r in {lp["reason"] for lp in held}}
    # independently: each held loop against the true relative pose of its keyframes' video frames
    assert held, "the episode's short sessions leave loops waiting for a second one"
    video = {k["id"]: k["video_index"] for k in json.loads((tmp_path / "keyframes.json").read_text())}
    gt = read_episode(contact_loss_episode).object_T_sensor
    for reason, m in by_reason.items():
        correct = 0
        for lp in (lp for lp in held if lp["reason"] == reason):
            err = np.linalg.inv(np.linalg.inv(gt[video[lp["ref_id"]]]) @ gt[video[lp["tar_id"]]]) @ np.array(
                lp["ref_T_tar"])
            angle = np.degrees(np.arccos(np.clip((np.trace(err[:3, :3]) - 1) / 2, -1, 1)))
            correct += bool(angle <= 1.0 and np.linalg.norm(err[:3, 3]) * 1e3 <= 0.3)
        assert m["correct"] == correct, reason


def test_all_groups_meshes_each_group_in_its_own_frame(contact_loss_episode, tmp_path):
    """``recon.all_groups``: besides the main group's mesh, every other group is meshed
    under ``groups/group_<label>/`` in the frame of its own first contact frame (that of
    ``poses_by_group.npy``): brought to the object by that frame's ground truth, it lies
    on the object."""
    cfg = Config()
    cfg.recon.all_groups = True
    src = GradientSequence(contact_loss_episode / "gt_gradients.npz", fps=25)
    res = OfflinePipeline(src, cfg, tmp_path, RunOptions(method="nf-kf", progress=False, mesh=True)).run()
    others = res.stats["reconstruction"]["other_groups"]
    assert len(others) == res.stats["groups"] - 1 >= 1
    ep = read_episode(contact_loss_episode)
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(ep.mesh()))
    meshed = 0
    for label, stats in others.items():
        folder = tmp_path / "groups" / f"group_{label}"
        if "skipped" in stats:  # fewer than two contact keyframes: nothing written
            assert not folder.exists()
            continue
        meshed += 1
        assert (folder / "mesh.ply").is_file() and not (folder / "mesh.png").exists()
        v = np.asarray(o3d.io.read_triangle_mesh(str(folder / "mesh_fused.ply")).vertices)
        T = ep.object_T_sensor[int(np.nonzero(res.frame_group == int(label))[0][0])]
        dist = scene.compute_distance(o3d.core.Tensor((v @ T[:3, :3].T + T[:3, 3]).astype(np.float32))).numpy()
        assert np.median(dist) < 0.05e-3, (label, np.median(dist))
    assert meshed >= 1


def test_cli_run_with_a_config_file(tracking_episode, tmp_path, capsys):
    """``tactile-slam run --config``: the file's settings reach the run (the resolved
    ``config.yaml`` holds them); a bad value exits 2 and writes no output folder."""
    good = tmp_path / "good.yaml"
    good.write_text("tracking:\n  keyframe_edge: midpoint\nrecon:\n  all_groups: true\n")
    out = tmp_path / "run"
    assert main(["run", str(tracking_episode / "gt_gradients.npz"), "--out", str(out), "--config", str(good),
                 "--method", "nf-kf", "--no-mesh"]) == 0
    resolved = Config.from_yaml(out / "config.yaml")
    assert resolved.tracking.keyframe_edge == "midpoint" and resolved.recon.all_groups is True
    bad = tmp_path / "bad.yaml"
    bad.write_text("tracking:\n  keyframe_edge: both\n")
    assert main(["run", str(tracking_episode / "gt_gradients.npz"), "--out", str(tmp_path / "bad_run"),
                 "--config", str(bad)]) == 2
    assert "keyframe_edge" in capsys.readouterr().err
    assert not (tmp_path / "bad_run").exists()


def test_config_yaml_names_the_model_a_run_decoded_with(tmp_path, capsys):
    """A run given ``--model`` writes that model into ``config.yaml``: the file alone
    reproduces the run's poses (before, it named no model and a re-run decoded with the
    shipped one)."""
    import shutil

    from tactile_slam.sim.episode import DEFAULT_COLOUR_MODEL

    shipped = Config().sensor.resolved_model_path()
    if shipped is None or not DEFAULT_COLOUR_MODEL.is_file():
        pytest.skip("needs the shipped calibration and colour models")
    episode = tmp_path / "episode"
    simulate_episode(episode, SimulationSettings(object="lime", kind="tracking", frames=24, level="image"))
    model = tmp_path / "models" / "mine.pt"
    model.parent.mkdir()
    shutil.copy(shipped, model)
    assert main(["run", str(episode), "--out", str(tmp_path / "a"), "--model", str(model), "--method", "nf-kf",
                 "--no-mesh"]) == 0
    written = Config.from_yaml(tmp_path / "a" / "config.yaml")
    assert written.sensor.model_path == str(model.resolve())
    assert json.loads((tmp_path / "a" / "stats.json").read_text())["model"] == str(model.resolve())
    model.rename(tmp_path / "models" / "moved.pt")  # the re-run must read the file the config names
    assert main(["run", str(episode), "--out", str(tmp_path / "b"), "--config", str(tmp_path / "a" / "config.yaml"),
                 "--method", "nf-kf", "--no-mesh"]) == 2
    assert "calibration model not found" in capsys.readouterr().err and not (tmp_path / "b").exists()
    (tmp_path / "models" / "moved.pt").rename(model)
    assert main(["run", str(episode), "--out", str(tmp_path / "b"), "--config", str(tmp_path / "a" / "config.yaml"),
                 "--method", "nf-kf", "--no-mesh"]) == 0
    np.testing.assert_array_equal(np.load(tmp_path / "a" / "poses.npy"), np.load(tmp_path / "b" / "poses.npy"))
