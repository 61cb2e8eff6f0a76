"""The online pipeline (tracker here, back end in a worker process), the real-time
feed and the pose stream, on short simulated gradient-level episodes."""

from __future__ import annotations

import json
import os
import signal
import threading
import time
from dataclasses import replace

import numpy as np
import pytest
import torch

from tactile_slam.cli.main import main
from tactile_slam.config import Config
from tactile_slam.eval.tracking_metrics import per_axis_mae
from tactile_slam.geometry.frame import InputError
from tactile_slam.io.frames import RawFrame, SequenceSource
from tactile_slam.io.gradients import GradientSequence
from tactile_slam.io.replay import RealtimeFeed
from tactile_slam.pipeline.offline import OfflinePipeline, RunOptions
from tactile_slam.pipeline.online import (
    KeyframeMap,
    OnlineOptions,
    OnlinePipeline,
    PoseUpdate,
    pack_keyframe,
    unpack_keyframe,
)
from tactile_slam.pipeline.stream import PoseEvent, PoseStream
from tactile_slam.sim.episode import SimulationSettings, read_episode, simulate_episode
from tactile_slam.tracking.keyframe import Keyframe

ONLINE_KEYS = {"frames_dropped", "latency_ms", "keyframes_skipped_for_loops", "backend_error", "stopped_by"}


@pytest.fixture(scope="module")
def episode(tmp_path_factory):
    # long enough for sessions to meet twice (groups merge on two agreeing loops) before
    # the last keyframes, so that the stream reports a loop correction
    out = tmp_path_factory.mktemp("ep_online")
    return simulate_episode(out, SimulationSettings(object="seed", kind="contact_loss", frames=520, seed=4))


def source(ep):
    return GradientSequence(ep / "gt_gradients.npz", fps=25)


@pytest.fixture(scope="module")
def offline(episode, tmp_path_factory):
    # one torch thread, as the online back end's worker: sums then add in the same order
    # on both sides, so the lossless run can be compared to the last rounding
    out = tmp_path_factory.mktemp("offline")
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        return OfflinePipeline(source(episode), Config(), out, RunOptions(progress=False, mesh=False)).run()
    finally:
        torch.set_num_threads(threads)


def online(ep, out, stream=None, **kw):
    opts = OnlineOptions(progress=False, mesh=kw.pop("mesh", False), rate=kw.pop("rate", None), **kw)
    return OnlinePipeline(source(ep), Config(), out, opts, stream=stream)


def gt_mae(ep, res):
    gt = read_episode(ep).object_T_sensor
    sel = res.frame_group >= 0
    g = res.frame_group[sel]
    main_group = np.bincount(g).argmax()
    sel &= res.frame_group == main_group
    first = int(np.nonzero(sel)[0][0])
    return per_axis_mae(res.poses_by_group, np.linalg.inv(gt[first]) @ gt, sel)


# ---------------------------------------------------------------- pipeline


def test_lossless_online_equals_offline(episode, offline, tmp_path):
    """Every frame delivered and every keyframe given loop detection: the worker sees
    exactly the offline keyframe sequence, so the trajectories coincide."""
    events = []
    stream = PoseStream(maxlen=1000)
    stream.add_callback(events.append)
    res = online(episode, tmp_path, stream=stream, skip_loops=False, tracker_threads=1).run()
    assert offline.stats["loops"] >= 1  # the episode exercises loop closure
    np.testing.assert_array_equal(res.frame_group, offline.frame_group)
    has = res.frame_group >= 0
    np.testing.assert_allclose(res.poses_by_group[has], offline.poses_by_group[has], atol=1e-9)
    s = json.loads((tmp_path / "stats.json").read_text())
    assert ONLINE_KEYS <= set(s) and s["completed"] and s["stopped_by"] == "end_of_stream"
    assert s["frames_dropped"] == 0 and s["keyframes_skipped_for_loops"] == 0 and s["backend_error"] is None
    assert s["loops"] == offline.stats["loops"] and s["keyframes"] == offline.stats["keyframes"]
    assert np.isfinite(s["latency_ms"]["p95"]) and s["latency_ms"]["p95"] >= s["latency_ms"]["median"] > 0
    for name in ("poses.npy", "trajectory_tum.txt", "keyframes.json", "loops.json", "pose_graph.g2o"):
        assert (tmp_path / name).is_file()
    # one event per frame, in order; poses of the stream are finite 4x4 float64 and inverse pairs
    assert [e.index for e in events] == list(range(len(res.poses)))
    tracked = [e for e in events if e.in_contact]
    assert len(tracked) == int(has.sum()) and sum(e.loop_corrected for e in events) >= 1
    for e in tracked:
        assert e.map_T_sensor.dtype == torch.float64 and e.map_T_sensor.shape == (4, 4)
        torch.testing.assert_close(e.map_T_sensor @ e.sensor_T_object, torch.eye(4, dtype=torch.float64))
    assert all(e.map_T_sensor is None and e.group == -1 for e in events if not e.in_contact)


def test_cli_online_with_skipping_close_to_offline(episode, offline, tmp_path, capsys):
    """The paper's online mode (loop detection for the newest queued keyframe only),
    through the CLI: accuracy within a bound of the offline run."""
    out = tmp_path / "on"
    npz = str(episode / "gt_gradients.npz")
    assert main(["run", npz, "--out", str(out), "--online", "--rate", "0", "--no-mesh", "--no-progress",
                 "--jsonl", str(tmp_path / "poses.jsonl")]) == 0
    printed = capsys.readouterr().out
    assert "online:" in printed
    s = json.loads((out / "stats.json").read_text())
    assert ONLINE_KEYS <= set(s) and 0 <= s["keyframes_skipped_for_loops"] < s["keyframes"]
    assert s["keyframes_depth_unknown"] == 0 and ("sessions began inside a contact" in printed) == \
        (s["registration_breaks"] > 0)
    from tactile_slam.pipeline.offline import RunResult

    res = RunResult(np.load(out / "poses.npy"), np.load(out / "poses_by_group.npy"),
                    np.load(out / "frame_group.npy"), [])
    on, off = gt_mae(episode, res), gt_mae(episode, offline)
    for k in ("x_mm", "y_mm", "z_mm"):
        assert on[k] <= off[k] + 0.05, (on, off)
    for k in ("rx_deg", "ry_deg", "rz_deg"):
        assert on[k] <= off[k] + 0.5, (on, off)
    lines = (tmp_path / "poses.jsonl").read_text().splitlines()
    assert len(lines) == s["frames"] and {"map_T_sensor", "latency_ms", "loop_corrected"} <= set(json.loads(lines[0]))
    # each published score is the one frames.csv holds for that frame
    table = np.genfromtxt(out / "frames.csv", delimiter=",", names=True)
    events = [json.loads(line) for line in lines]
    for name in ("ccs", "scr", "conditioning"):
        sent = np.array([np.nan if e[name] is None else e[name] for e in events])
        np.testing.assert_allclose(sent, table[name][[e["index"] for e in events]], rtol=1e-5)
    contact = np.array([e["in_contact"] for e in events])
    assert not np.isfinite(sent[~contact]).any()  # only the session heads in contact have none
    assert np.isfinite(sent[contact]).sum() == contact.sum() - s["sessions"]


def test_stop_mid_contact_saves_everything(episode, tmp_path):
    pipe = online(episode, tmp_path, mesh=True, preview_every_s=1e9)  # preview written at the end only
    stream = pipe.start()
    n_contact = 0
    for event in stream:  # a policy loop reading the stream
        n_contact += event.in_contact
        if n_contact == 12:
            pipe.stop()
    res = pipe.join(timeout=600)
    s = res.stats
    assert s["stopped_by"] == "stopped" and not s["completed"]
    assert 12 <= s["frames"] < len(read_episode(episode))
    last = int(np.nonzero(res.frame_group >= 0)[0][-1])
    assert last >= s["frames"] - 2  # it stopped in contact
    kfs = json.loads((tmp_path / "keyframes.json").read_text())
    assert kfs[-1]["video_index"] == last  # the session tail was flushed as a keyframe
    for name in ("poses.npy", "trajectory_tum.txt", "frames.csv", "stats.json", "pose_graph.g2o", "mesh_fused.ply",
                 "preview/preview.ply", "preview/preview.png"):
        assert (tmp_path / name).is_file(), name
    assert np.isfinite(np.load(tmp_path / "poses.npy")[last]).all()
    table = np.genfromtxt(tmp_path / "frames.csv", delimiter=",", names=True)
    assert len(table) == len(res.poses) and table["is_keyframe"][last] == 1 and np.isfinite(table["ccs"][last])


def test_ctrl_c_saves_and_exits_cleanly(episode, tmp_path):
    stream = PoseStream()
    stream.add_callback(lambda e: e.index == 20 and os.kill(os.getpid(), signal.SIGINT))
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        res = online(episode, tmp_path, stream=stream).run()
    finally:
        signal.signal(signal.SIGINT, previous)
    assert res.stats["stopped_by"] == "interrupted" and not res.stats["completed"]
    assert res.stats["backend_error"] is None  # the worker ignores Ctrl+C and finishes
    assert (tmp_path / "poses.npy").is_file() and (tmp_path / "stats.json").is_file()


def test_killed_backend_is_reported_and_tracking_goes_on(episode, tmp_path):
    pipe = online(episode, tmp_path)
    killed = threading.Event()

    def kill(event):
        if event.keyframe_id >= 1 and not killed.is_set():
            os.kill(pipe.backend.pid, signal.SIGKILL)
            killed.set()

    pipe.stream.add_callback(kill)
    after = []
    for event in pipe.start():
        if killed.is_set() and event.in_contact:
            after.append(event)
            if len(after) == 15:
                pipe.stop()
    res = pipe.join(timeout=600)
    s = res.stats
    assert killed.is_set() and "exited with code -9" in s["backend_error"]
    assert s["stopped_by"] == "stopped"
    assert all(torch.isfinite(e.map_T_sensor).all() for e in after)
    # poses of the frames tracked after the kill are saved (odometry on top of the last solve)
    contact = res.frame_group >= 0
    assert contact.sum() == s["contact_frames"] and np.isfinite(res.poses_by_group[contact]).all()


def test_cli_live_without_camera(tmp_path, capsys):
    assert main(["live", "--out", str(tmp_path / "o"), "--camera", "no-such-sensor-xyz", "--no-progress"]) == 2
    assert "no camera named 'no-such-sensor-xyz'" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


def test_rejects_image_sift_and_empty_source(tmp_path):
    with pytest.raises(ValueError, match="gs-imagesift"):
        OnlinePipeline(ListSource([]), Config(), tmp_path, OnlineOptions(method="gs-imagesift"))
    with pytest.raises(InputError, match="no frames"):
        OnlinePipeline(ListSource([]), Config(), tmp_path, OnlineOptions(method="nf-kf", rate=None)).run()


# ---------------------------------------------------------------- feed


class ListSource(SequenceSource):
    def __init__(self, frames, fps=25.0, fail_at=None):
        self.frames, self.fps, self.shape, self.name, self.fail_at = frames, fps, (4, 4), "list", fail_at

    def __len__(self):
        return len(self.frames)

    def frame(self, position):
        if position == self.fail_at:
            raise InputError("read failed")
        return self.frames[position]


def raw(n):
    return [RawFrame(i, i / 25.0, gradients=np.zeros((4, 4, 2), np.float32)) for i in range(n)]


def test_feed_counts_every_drop():
    feed = RealtimeFeed(ListSource(raw(60), fps=500.0), rate=1.0, capacity=1)
    got = []
    for a in feed:
        got.append(a.frame.index)
        time.sleep(0.01)  # a tracker slower than the 2 ms frame period
    assert feed.dropped > 0 and len(got) + feed.dropped == feed.stats.read == 60
    assert sorted(got + feed.stats.dropped_indices) == list(range(60))
    assert got == sorted(got) and got[-1] == 59  # the newest frames survive


def test_feed_lossless_and_paced():
    feed = RealtimeFeed(ListSource(raw(10), fps=100.0), rate=None, capacity=1)
    assert [a.frame.index for a in feed] == list(range(10)) and feed.dropped == 0
    feed = RealtimeFeed(ListSource(raw(6), fps=50.0), rate=1.0, capacity=8)
    arrivals = [a.arrival for a in feed]
    np.testing.assert_allclose(np.diff(arrivals), 0.02, atol=1e-9)  # due times at the native rate


def test_feed_errors():
    with pytest.raises(InputError, match="rate"):
        RealtimeFeed(ListSource(raw(1)), rate=0.0)
    with pytest.raises(InputError, match="capacity"):
        RealtimeFeed(ListSource(raw(1)), capacity=0)
    feed = RealtimeFeed(ListSource(raw(5), fail_at=3), rate=None)
    got = []
    with pytest.raises(InputError, match="read failed"):
        for a in feed:
            got.append(a.frame.index)
    assert got == [0, 1, 2]


# ---------------------------------------------------------------- stream


def test_pose_stream_consumers(tmp_path):
    stream = PoseStream(maxlen=2, jsonl=tmp_path / "e.jsonl")
    seen, boom = [], []
    stream.add_callback(seen.append)
    stream.add_callback(lambda e: boom.append(1 / 0))
    assert stream.latest() is None and stream.get(timeout=0.01) is None
    T = torch.eye(4, dtype=torch.float64)
    for i in range(5):
        stream.publish(PoseEvent(i, i / 25, True, T, T, latency_ms=1.0))
    assert stream.latest().index == 4 and stream.missed == 3
    stream.close()
    assert [e.index for e in stream] == [3, 4]  # the newest two; iteration ends at close
    assert [e.index for e in seen] == list(range(5)) and len(stream.callback_errors) == 5
    lines = [json.loads(x) for x in (tmp_path / "e.jsonl").read_text().splitlines()]
    assert [x["index"] for x in lines] == list(range(5)) and lines[0]["map_T_sensor"] == T.tolist()
    assert lines[0]["ccs"] is None  # NaN -> null
    with pytest.raises(ValueError, match="maxlen"):
        PoseStream(maxlen=0)


# ---------------------------------------------------------------- keyframes across processes


def make_keyframe(kf_id, session, new_session, dtype=torch.float32, seed=0):
    g = torch.Generator().manual_seed(seed)
    from tactile_slam.geometry.frame import Frame

    frame = Frame(torch.randn(1, 6, 8, 2, generator=g, dtype=dtype), torch.randn(1, 6, 8, generator=g, dtype=dtype),
                  torch.rand(1, 6, 8, generator=g) > 0.5, torch.randn(1, 6, 8, 3, generator=g, dtype=dtype),
                  torch.randn(1, 6, 8, generator=g, dtype=dtype), torch.tensor([True]), torch.tensor([True]),
                  torch.tensor([7 + kf_id]),
                  torch.tensor([0.5], dtype=torch.float64), 0.0634)
    prev_T_kf = torch.eye(4, dtype=torch.float64)
    prev_T_kf[0, 3] = 1e-3 * (kf_id + 1)
    return Keyframe(kf_id, session, frame, new_session, prev_T_kf)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_pack_round_trip_one_shared_buffer(dtype):
    kf = make_keyframe(3, 1, False, dtype)
    packed = pack_keyframe(kf)
    assert packed.buffer.is_shared() and packed.buffer.shape == (6, 6, 8)  # contact reaches every border
    back = unpack_keyframe(packed)
    assert back.frame.gradients is None and back.frame.shape == (6, 8) and len(back.frame) == 1
    for name in ("height", "normals", "curvature"):
        stored, got, want = getattr(back.maps.box, name), getattr(back.frame, name), getattr(kf.frame, name)
        assert stored.data_ptr() >= packed.buffer.data_ptr()  # the record is a view of the buffer, no copy
        assert got.shape == want.shape
        torch.testing.assert_close(got, want.float())
    assert torch.equal(back.frame.contact, kf.frame.contact) and back.frame.contact.dtype == torch.bool
    assert (back.id, back.session, back.new_session, back.video_index) == (3, 1, False, 10)
    torch.testing.assert_close(back.prev_T_kf, kf.prev_T_kf)
    assert back.depth_known and kf.depth_known
    unknown = Keyframe(4, 1, replace(kf.frame, depth_known=torch.tensor([False])), False, kf.prev_T_kf)
    assert not unpack_keyframe(pack_keyframe(unknown)).depth_known
    assert not back.decoded
    decoded = Keyframe(5, 1, replace(kf.frame, decoded=True), False, kf.prev_T_kf)
    assert unpack_keyframe(pack_keyframe(decoded)).decoded
    with pytest.raises(ValueError, match="one frame"):
        pack_keyframe(Keyframe(0, 0, kf.frame.cat([kf.frame, kf.frame]), True, kf.prev_T_kf))


def test_pack_holds_the_contact_box_only():
    """A small touch crosses the process boundary as its box plus the margin; the worker's
    full maps equal the tracker's within that box and are flat gel outside it."""
    kf = make_keyframe(0, 0, True)
    g = torch.Generator().manual_seed(1)
    h, w = 60, 80
    contact = torch.zeros(1, h, w, dtype=torch.bool)
    contact[0, 20:30, 40:52] = True
    frame = replace(kf.frame, gradients=None, height=torch.randn(1, h, w, generator=g), contact=contact,
                    normals=torch.randn(1, h, w, 3, generator=g), curvature=torch.randn(1, h, w, generator=g))
    packed = pack_keyframe(Keyframe(0, 0, frame, True, kf.prev_T_kf))
    assert packed.buffer.shape == (6, 10 + 16, 12 + 16) and (packed.top, packed.left) == (12, 32)
    full = unpack_keyframe(packed).frame
    box = (slice(None), slice(12, 38), slice(32, 60))
    for name in ("height", "normals", "curvature"):
        torch.testing.assert_close(getattr(full, name)[box], getattr(frame, name)[box])
    assert torch.equal(full.contact, contact)
    outside = torch.ones(1, h, w, dtype=torch.bool)
    outside[box] = False
    assert (full.height[outside] == 0).all() and (full.curvature[outside] == 0).all()
    assert torch.equal(full.normals[outside], torch.tensor([0.0, 0.0, 1.0]).expand(int(outside.sum()), 3))


def test_keyframe_map_chains_until_the_back_end_answers():
    kmap = KeyframeMap()
    kfs = [make_keyframe(0, 0, True), make_keyframe(1, 0, False), make_keyframe(2, 0, False), make_keyframe(3, 1, True)]
    for kf in kfs:
        kmap.add(kf)
    torch.testing.assert_close(kmap.start_T_kf[2], kfs[1].prev_T_kf @ kfs[2].prev_T_kf)
    assert kmap.group[2] == kmap.group[0] != kmap.group[3]
    # the back end answers for 0 and 1 with a corrected pose of 1 and a merge of nothing
    moved = torch.eye(4, dtype=torch.float64)
    moved[1, 3] = 5e-3
    kmap.apply(PoseUpdate(np.array([0, 1]), np.stack([np.eye(4), moved.numpy()]), np.array([0, 0]), 0, 0, 0))
    torch.testing.assert_close(kmap.start_T_kf[1], moved)
    torch.testing.assert_close(kmap.start_T_kf[2], moved @ kfs[2].prev_T_kf)  # re-chained on the answer
    assert kmap.group[2] == 0 and kmap.group[3] == 1  # the new session is its own group


# ---------------------------------------------------------------- live camera


class FakeCapture:
    """A sensor at 25 Hz: 10 contact-free frames, then a held press."""

    def __init__(self, background, press):
        self.background, self.press, self.reads = background, press, 0

    def isOpened(self):
        return True

    def set(self, prop, value):
        return True

    def read(self):
        time.sleep(0.04)
        self.reads += 1
        return True, (self.background if self.reads <= 10 else self.press).copy()

    def release(self):
        pass


def test_live_camera_held_press(mini_data, tmp_path):
    """The live path: a camera stream (background from its first frames, colour
    decoding), stopped from the pose stream; a held press tracks to the identity."""
    import cv2

    from tactile_slam.io.camera import CameraSource

    bg = cv2.imread(str(mini_data / "calibration" / "background.png"))
    press = cv2.imread(str(mini_data / "calibration" / "6.310mm" / "0" / "gelsight.png"))
    cam = CameraSource(0, open_capture=lambda i: FakeCapture(bg, press))
    pipe = OnlinePipeline(cam, Config(), tmp_path, OnlineOptions(method="nf-kf", progress=False, mesh=False))
    tracked = []
    for event in pipe.start():
        if event.in_contact:
            tracked.append(event)
            if len(tracked) == 6:
                pipe.stop()
    res = pipe.join(timeout=600)
    cam.close()
    s = res.stats
    assert s["stopped_by"] == "stopped" and s["frames"] >= 6 and s["frames_read"] >= s["frames"] + 10
    assert s["frames_read"] >= s["frames"] + 10 + s["frames_dropped"]  # background window, tracked, dropped
    for e in tracked:
        torch.testing.assert_close(e.map_T_sensor, torch.eye(4, dtype=torch.float64), atol=2e-5, rtol=0)
    assert np.isfinite(np.load(tmp_path / "poses.npy")).all(axis=(1, 2)).sum() == s["frames_with_pose"] >= 6
