"""What an online run leaves and says: pose_graph.png, the preview folder replaced by a
later run, the keyframes its pose events report, Ctrl+C on ``run --online``, and
``--jsonl -`` keeping standard output to JSON lines. On a 150-frame simulated
contact-loss episode (two touches)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from tactile_slam.cli.main import main
from tactile_slam.config import Config
from tactile_slam.io.gradients import GradientSequence
from tactile_slam.pipeline.online import OnlineOptions, OnlinePipeline
from tactile_slam.pipeline.outputs import clear_run_outputs
from tactile_slam.pipeline.stream import PoseStream
from tactile_slam.sim.episode import SimulationSettings, simulate_episode

pytestmark = pytest.mark.usefixtures("one_thread")

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


@pytest.fixture(scope="module")
def episode(tmp_path_factory):
    out = tmp_path_factory.mktemp("ep_online_outputs")
    return simulate_episode(out, SimulationSettings(object="seed", kind="contact_loss", frames=150, seed=1))


def online(ep, out, stream=None, **kw):
    opts = OnlineOptions(progress=False, mesh=False, rate=None, **kw)
    return OnlinePipeline(GradientSequence(ep / "gt_gradients.npz", fps=25), Config(), out, opts, stream=stream)


def test_pose_graph_png_written_and_a_stale_preview_replaced(episode, tmp_path):
    """The worker wrote loops.json and pose_graph.g2o but not the offline run's
    pose_graph.png; and a later run into the folder left an earlier run's preview/."""
    res = online(episode, tmp_path, preview_every_s=1e9).run()
    assert res.stats["keyframes"] >= 2 and res.stats["backend_error"] is None
    assert (tmp_path / "pose_graph.png").read_bytes().startswith(PNG_MAGIC)
    assert (tmp_path / "preview" / "preview.ply").is_file()
    online(episode, tmp_path, method="nf-kf").run()  # no back end: neither is this run's
    assert not (tmp_path / "preview").exists() and not (tmp_path / "pose_graph.png").exists()
    assert (tmp_path / "poses.npy").is_file()


def test_clearing_a_folder_removes_an_earlier_preview(tmp_path):
    (tmp_path / "preview").mkdir()
    (tmp_path / "preview" / "preview.png").write_bytes(PNG_MAGIC)
    (tmp_path / "notes.txt").write_text("mine")
    assert clear_run_outputs(tmp_path) == ["preview/"]
    assert not (tmp_path / "preview").exists() and (tmp_path / "notes.txt").is_file()


def test_events_report_every_keyframe_when_it_is_made(episode, tmp_path):
    """``is_keyframe`` marks session heads only: the lazy rule makes the previous frame
    a keyframe one event later, and that event's ``new_keyframes`` names it."""
    events = []
    stream = PoseStream(maxlen=1000)
    stream.add_callback(events.append)
    online(episode, tmp_path, stream=stream, method="nf-kf").run()
    kfs = json.loads((tmp_path / "keyframes.json").read_text())
    made = [i for e in events for i in e.new_keyframes]
    assert made == [k["video_index"] for k in kfs][:len(made)] and len(kfs) - len(made) in (0, 1)  # + a final tail
    assert [e.index for e in events if e.is_keyframe] == [k["video_index"] for k in kfs if k["new_session"]]
    lazy = 0
    for prev, e in zip([None, *events], events):
        for i in e.new_keyframes:
            if i == e.index:
                assert e.is_keyframe
            else:  # the previous frame, decided now
                assert prev is not None and i == prev.index and not prev.is_keyframe
                lazy += 1
    assert lazy >= 1 and lazy > len(kfs) - len(made) - 1  # the episode has keyframes made late


def test_ctrl_c_on_run_online_exits_130_and_says_so(episode, tmp_path, monkeypatch):
    """``run --online`` exited 0 on Ctrl+C, and stats.json had no ``error``."""
    publish = PoseStream.publish

    def interrupted_at_40(self, event):
        publish(self, event)
        if event.index == 40:
            raise KeyboardInterrupt  # where a Ctrl+C lands: the tracking loop

    monkeypatch.setattr(PoseStream, "publish", interrupted_at_40)
    out = tmp_path / "o"
    assert main(["run", str(episode / "gt_gradients.npz"), "--out", str(out), "--online", "--rate", "0",
                 "--no-mesh", "--no-progress"]) == 130
    s = json.loads((out / "stats.json").read_text())
    assert s["stopped_by"] == "interrupted" and s["completed"] is False
    assert s["error"].startswith("KeyboardInterrupt") and s["backend_error"] is None
    assert s["frames"] == 41 and (out / "pose_graph.png").is_file()  # the frames before it are saved


def test_jsonl_to_stdout_carries_json_lines_only(episode, tmp_path, capsys):
    """With ``--jsonl -`` the summary, the caveats and the "replaced the outputs of an
    earlier run" line went to standard output between the pose events."""
    out = tmp_path / "o"
    args = ["run", str(episode / "gt_gradients.npz"), "--out", str(out), "--online", "--rate", "0", "--no-mesh",
            "--no-progress", "--method", "nf-kf", "--jsonl", "-"]
    for run in range(2):  # the second replaces the first's outputs, and says so
        assert main(args) == 0
        captured = capsys.readouterr()
        events = [json.loads(line) for line in captured.out.splitlines()]
        frames = json.loads((out / "stats.json").read_text())["frames"]
        assert len(events) == frames and {"index", "map_T_sensor", "new_keyframes"} <= set(events[0])
        assert "online:" in captured.err
        assert ("replaced the outputs of an earlier run" in captured.err) == (run == 1)
