"""The online pipeline: tracking in this process, loop closure and the pose graph in a
worker process, frames delivered in real time (method.md 5.2, 6.4, 7.2).

``OnlinePipeline(source, config, out_dir, OnlineOptions(...)).run()`` replays a
recording at its native frame rate (or reads a live camera) through a
:class:`~tactile_slam.io.replay.RealtimeFeed`, computes geometry and tracks each frame
as it arrives, publishes a :class:`~tactile_slam.pipeline.stream.PoseEvent` per frame
on :attr:`OnlinePipeline.stream`, and sends every keyframe to the back-end worker.

Keyframes cross the process boundary as one float32 buffer in shared memory per
keyframe (:func:`pack_keyframe`): the maps around the contact are copied once into it,
the worker maps the same pages, and the pipeline's own record of the keyframe is a view
of that buffer.

The worker takes the keyframes queued since its last step as one batch: each gets
its odometry factor and coverage update, but only the newest gets loop detection
(online skipping); the skipped ones are counted. After each batch it sends every
keyframe's solved pose back. The tracker poses frames with the latest poses it has,
chaining keyframes the worker has not answered for yet by odometry
(:class:`KeyframeMap`).

End of stream, :meth:`OnlinePipeline.stop`, Ctrl+C (``KeyboardInterrupt``) or a dead
worker never lose work: the tracker flushes its session tail, the worker (if alive)
finishes its final solve, and every output of the offline pipeline is written for the
frames seen so far (``poses.npy``, ``trajectory_tum.txt``, ``frames.csv``, ``keyframes.json``,
``loops.json``, ``pose_graph.g2o``, ``pose_graph.png``, the mesh), plus the online statistics in
``stats.json`` (``frames_dropped``, ``latency_ms``, ``keyframes_skipped_for_loops``,
``backend_error``, ``stopped_by``; after Ctrl+C ``error``, as offline). See ``docs/online.md``.
"""

from __future__ import annotations

import contextlib
import itertools
import os
import queue
import signal
import sys
import threading
import time
import traceback
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
import torch.multiprocessing as mp
from tqdm import tqdm

from tactile_slam.backend import BackEnd
from tactile_slam.config import Config
from tactile_slam.geometry.frame import CroppedFrame, Frame, InputError, crop_to_contact
from tactile_slam.io.dataset import collate
from tactile_slam.io.frames import FrameSource
from tactile_slam.io.replay import RealtimeFeed
from tactile_slam.pipeline.offline import LOOP_MODES, OfflinePipeline, RunOptions, RunResult, tracker_counts
from tactile_slam.pipeline.outputs import write_json, write_pose_graph_png
from tactile_slam.pipeline.stream import PoseEvent, PoseStream
from tactile_slam.pipeline.visualizer import NullVisualizer
from tactile_slam.tracking.keyframe import Keyframe


@dataclass
class OnlineOptions(RunOptions):
    """How to run online (adds to :class:`~tactile_slam.pipeline.offline.RunOptions`;
    ``batch_size`` is ignored: frames are processed one by one as they arrive).

    Attributes:
        rate: replay speed as a multiple of a recording's native frame rate; ``None``
            replays losslessly as fast as the tracker goes (live cameras pace themselves).
        buffer_frames: frames that may wait for the tracker before the oldest is dropped.
        skip_loops: when the back end is busy, run loop detection for the newest queued
            keyframe only (the paper's online mode); ``False`` detects for every keyframe
            and lets the back end fall behind.
        preview_every_s: the worker writes ``preview/preview.ply`` and
            ``preview/preview.png`` (the fused preview surface, each group in its own
            start frame) at most this often and at the end; ``None``: off.
        backend_threads: torch threads of the worker.
        tracker_threads: torch threads of this process during the run (``None``: unchanged).
        jsonl: also write every pose event as a JSON line to this path (``"-"``: stdout).
        start_timeout_s: how long to wait for the worker to start.
    """

    rate: float | None = 1.0
    buffer_frames: int = 3
    skip_loops: bool = True
    preview_every_s: float | None = None
    backend_threads: int = 1
    tracker_threads: int | None = None
    jsonl: str | None = None
    start_timeout_s: float = 300.0


# ---------------------------------------------------------------- keyframes across processes

_CHANNELS = (("height", 1), ("normals", 3), ("curvature", 1), ("contact", 1))


@dataclass
class PackedKeyframe:
    """A keyframe as one ``(6, h, w)`` float32 shared-memory buffer of its maps around the
    contact (height, normals x/y/z, curvature, contact: a :class:`CroppedFrame`, whose
    box starts at ``top``, ``left`` of a ``full_shape`` image) plus small metadata;
    pickles to a handle of that buffer, not its contents."""

    id: int
    session: int
    new_session: bool
    prev_T_kf: np.ndarray
    index: int
    timestamp: float
    in_contact: bool
    depth_known: bool
    mm_per_px: float
    decoded: bool
    top: int
    left: int
    full_shape: tuple[int, int]
    buffer: torch.Tensor


def pack_keyframe(kf: Keyframe) -> PackedKeyframe:
    """Copy a keyframe's maps (``B = 1``) around its contact into one shared-memory buffer."""
    if len(kf.maps) != 1:
        raise ValueError(f"a keyframe holds one frame, got {len(kf.maps)}")
    crop = kf.maps if isinstance(kf.maps, CroppedFrame) else crop_to_contact(kf.maps)
    box = crop.box
    buf = torch.empty(sum(c for _, c in _CHANNELS), *box.shape, dtype=torch.float32).share_memory_()
    buf[0] = box.height[0]
    buf[1:4] = box.normals[0].permute(2, 0, 1)
    buf[4] = box.curvature[0]
    buf[5] = box.contact[0]
    return PackedKeyframe(kf.id, kf.session, kf.new_session, kf.prev_T_kf.cpu().numpy().copy(),
                          int(box.index[0]), float(box.timestamp[0]), bool(box.in_contact[0]), bool(box.depth_known[0]),
                          box.mm_per_px, box.decoded,
                          crop.top, crop.left, tuple(crop.full_shape), buf)


def unpack_keyframe(p: PackedKeyframe) -> Keyframe:
    """A :class:`Keyframe` whose cropped maps are views of the packed buffer (the contact
    mask is the only copy)."""
    b = p.buffer
    box = Frame(
        gradients=None,
        height=b[0][None],
        contact=(b[5] > 0.5)[None],
        normals=b[1:4].permute(1, 2, 0)[None],
        curvature=b[4][None],
        in_contact=torch.tensor([p.in_contact]),
        depth_known=torch.tensor([p.depth_known]),
        index=torch.tensor([p.index], dtype=torch.int64),
        timestamp=torch.tensor([p.timestamp], dtype=torch.float64),
        mm_per_px=p.mm_per_px,
        decoded=p.decoded,
    )
    crop = CroppedFrame(box=box, top=p.top, left=p.left, full_shape=p.full_shape)
    return Keyframe(p.id, p.session, crop, p.new_session, torch.as_tensor(p.prev_T_kf, dtype=torch.float64))


# ---------------------------------------------------------------- poses on the tracker side


@dataclass
class PoseUpdate:
    """The back end's state after one step.

    Attributes:
        ids: ``(K,)`` keyframe ids processed so far.
        poses: ``(K, 4, 4)`` float64 metres, ``start_T_kf`` in each keyframe's group frame.
        groups: ``(K,)`` group ids.
        loops / merges: totals so far.
        skipped: keyframes so far that got no loop detection.
        step_s: worker seconds per keyframe of this step.
    """

    ids: np.ndarray
    poses: np.ndarray
    groups: np.ndarray
    loops: int
    merges: int
    skipped: int
    step_s: list[float] = field(default_factory=list)


class KeyframeMap:
    """Keyframe poses as the tracker knows them: the back end's latest answer, and
    keyframes it has not answered for yet chained by odometry from their predecessor in
    the session (a session head alone starts its own group at the identity, labelled by
    its session id, as the back end labels a group by its root session).

    ``start_T_kf[id]`` ``(4, 4)`` float64 metres and ``group[id]`` (the same interface as
    :class:`~tactile_slam.backend.BackEnd` and
    :class:`~tactile_slam.pipeline.odometry.OdometryMap`).
    """

    def __init__(self) -> None:
        self.start_T_kf: dict[int, torch.Tensor] = {}
        self.group: dict[int, int] = {}
        self._pending: list[Keyframe] = []

    def _place(self, kf: Keyframe) -> None:
        # within a session keyframe ids are consecutive: the predecessor is id - 1
        prev = kf.id - 1
        if kf.new_session or prev not in self.start_T_kf:
            self.start_T_kf[kf.id] = torch.eye(4, dtype=torch.float64)
            self.group[kf.id] = kf.session  # its own group, labelled like the back end's (root session)
        else:
            self.start_T_kf[kf.id] = self.start_T_kf[prev] @ kf.prev_T_kf
            self.group[kf.id] = self.group[prev]

    def add(self, kf: Keyframe) -> None:
        """A keyframe just sent to the back end."""
        self._pending.append(kf)
        self._place(kf)

    def apply(self, update: PoseUpdate) -> None:
        """Take the back end's poses, then re-chain the keyframes it has not seen."""
        for i, pose, g in zip(update.ids.tolist(), update.poses, update.groups.tolist()):
            self.start_T_kf[i] = torch.from_numpy(pose)
            self.group[i] = g
        answered = set(update.ids.tolist())
        self._pending = [k for k in self._pending if k.id not in answered]
        for kf in self._pending:
            self._place(kf)


# ---------------------------------------------------------------- the worker


def _update(backend: BackEnd, skipped: int, step_s: list[float]) -> PoseUpdate:
    ids = np.array(list(backend.keyframes), dtype=np.int64)
    stack = backend.graph.poses(ids.tolist()).numpy() if len(ids) else np.zeros((0, 4, 4))
    group = backend.group
    return PoseUpdate(ids, stack, np.array([group[i] for i in ids.tolist()], dtype=np.int64),
                      backend.stats.loops, backend.stats.merges, skipped, step_s)


def _write_preview(preview, backend: BackEnd, out: Path) -> None:
    from tactile_slam.recon import ReconError

    preview.update_poses(dict(backend.start_T_kf))
    try:
        folder = out / "preview"
        folder.mkdir(parents=True, exist_ok=True)
        preview.save_ply(folder / "preview.tmp.ply").replace(folder / "preview.ply")
        preview.save_png(folder / "preview.tmp.png").replace(folder / "preview.png")
    except ReconError:
        pass  # nothing with contact yet


def backend_worker(config: Config, loop_mode: str, inbox, outbox, skip_loops: bool, out_dir: str,
                   preview_every_s: float | None, threads: int) -> None:
    """Worker process body: keyframe batches in, :class:`PoseUpdate` out.

    Messages in: ``("kf", PackedKeyframe)``, ``("finish",)``. Out: ``("ready", pid)``,
    ``("update", PoseUpdate)`` per batch, ``("final", PoseUpdate, stats)`` after the
    final solve (``loops.json``, ``loops_held.json``, ``pose_graph.g2o`` and
    ``pose_graph.png`` written to ``out_dir``), or ``("error", traceback)``.
    """
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl+C is the tracker's to handle
    torch.set_num_threads(threads)
    try:
        backend = BackEnd(config, loop_mode)
        preview = None
        if preview_every_s is not None:
            from tactile_slam.recon.preview import PreviewSurface

            preview = PreviewSurface(config)
        last_preview = time.monotonic()
        out = Path(out_dir)
        outbox.put(("ready", os.getpid()))
        skipped, finish = 0, False
        while not finish:
            msgs = [inbox.get()]
            while True:
                try:
                    msgs.append(inbox.get_nowait())
                except queue.Empty:
                    break
            kfs = [unpack_keyframe(m[1]) for m in msgs if m[0] == "kf"]
            finish = any(m[0] == "finish" for m in msgs)
            step_s = []
            for i, kf in enumerate(kfs):
                detect = not skip_loops or i == len(kfs) - 1
                t0 = time.perf_counter()
                backend.add(kf, detect=detect)
                step_s.append(time.perf_counter() - t0)
                skipped += not detect
                if preview is not None:
                    preview.add(kf, backend.start_T_kf[kf.id])
            if finish:
                backend.finish()
            # at the end always (the finish message may arrive in a batch without keyframes)
            if preview is not None and backend.keyframes and (
                    finish or (kfs and time.monotonic() - last_preview >= preview_every_s)):
                _write_preview(preview, backend, out)
                last_preview = time.monotonic()
            if not finish:
                outbox.put(("update", _update(backend, skipped, step_s)))
        stats = backend.summary()
        if backend.keyframes:
            backend.write(out)
            write_pose_graph_png(out / "pose_graph.png", backend)
        outbox.put(("final", _update(backend, skipped, []), stats))
    except BaseException:  # reported to the tracker, which carries on without us
        outbox.put(("error", traceback.format_exc()))


@contextlib.contextmanager
def _main_module_hidden():
    """Start spawned children without re-running the caller's script: the worker needs
    only this package, and a user's script (a policy loop) need not be guarded by
    ``if __name__ == "__main__"``."""
    main = sys.modules["__main__"]
    saved = {k: main.__dict__.pop(k) for k in ("__file__", "__spec__") if k in main.__dict__}
    if "__spec__" in saved:
        main.__spec__ = None
    try:
        yield
    finally:
        main.__dict__.update(saved)


class BackendProcess:
    """The worker process and its two queues, seen from the tracker.

    Args:
        config, loop_mode: the back end's settings.
        skip_loops, out_dir, preview_every_s, threads: see :class:`OnlineOptions`.
    """

    def __init__(self, config: Config, loop_mode: str, skip_loops: bool, out_dir: Path,
                 preview_every_s: float | None, threads: int):
        ctx = mp.get_context("spawn")  # fork is unsafe after torch's thread pools start
        self.inbox, self.outbox = ctx.Queue(), ctx.Queue()
        self.process = ctx.Process(
            target=backend_worker, name="tactile-slam-backend", daemon=True,
            args=(config, loop_mode, self.inbox, self.outbox, skip_loops, str(out_dir), preview_every_s, threads),
        )
        with _main_module_hidden():
            self.process.start()
        self.pid: int | None = None
        self.error: str | None = None
        self.final: tuple[PoseUpdate, dict] | None = None
        self.sent = 0

    @property
    def alive(self) -> bool:
        return self.error is None and self.final is None and self.process.exitcode is None

    def _dead(self, why: str) -> None:
        if self.error is None:
            self.error = why
        self.inbox.cancel_join_thread()  # never block our exit on a dead reader

    def wait_ready(self, timeout: float) -> None:
        """Block until the worker runs.

        Raises:
            RuntimeError: it failed or did not start in time.
        """
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            try:
                msg = self.outbox.get(timeout=0.2)
            except queue.Empty:
                if self.process.exitcode is not None:
                    break
                continue
            if msg[0] == "ready":
                self.pid = msg[1]
                return
            if msg[0] == "error":
                self._dead(msg[1])
                break
        if self.error is None and self.process.exitcode is not None:
            self._dead(f"it exited with code {self.process.exitcode}")
        self.terminate()
        raise RuntimeError(f"the back-end process did not start: {self.error or 'timed out'}")

    def send(self, packed: PackedKeyframe) -> bool:
        """Queue a keyframe; ``False`` (and nothing sent) once the worker is gone."""
        if not self.alive:
            return False
        self.inbox.put(("kf", packed))
        self.sent += 1
        return True

    def poll(self, timeout: float = 0.0) -> list[PoseUpdate]:
        """Updates that arrived (waiting up to ``timeout`` for the first); notices a
        dead worker."""
        updates = []
        while self.error is None and self.final is None:
            try:
                msg = self.outbox.get(timeout=timeout) if timeout > 0 and not updates else self.outbox.get_nowait()
            except queue.Empty:
                if self.process.exitcode is not None:
                    self._dead(f"the back-end process exited with code {self.process.exitcode} "
                               f"after {self.sent} keyframes were sent")
                break
            if msg[0] == "update":
                updates.append(msg[1])
            elif msg[0] == "final":
                self.final = (msg[1], msg[2])
                updates.append(msg[1])
            elif msg[0] == "error":
                self._dead(f"the back end failed:\n{msg[1]}")
        return updates

    def finish(self) -> list[PoseUpdate]:
        """Ask for the final solve and wait for it (or for the worker's death)."""
        updates = []
        if self.alive:
            self.inbox.put(("finish",))
            while self.alive or (self.error is None and self.final is None):
                updates += self.poll(timeout=0.5)
        self.terminate()
        return updates

    def terminate(self) -> None:
        if self.process.exitcode is None:
            self.process.join(timeout=5.0 if self.final is not None else 0.0)
        if self.process.exitcode is None:
            self.process.kill()
            self.process.join()


# ---------------------------------------------------------------- the pipeline


class OnlinePipeline(OfflinePipeline):
    """Real-time tracking with loop closure in a parallel process.

    Args:
        source: a recording (replayed at ``options.rate``) or a live camera.
        config: settings; written back resolved to ``config.yaml``.
        out_dir: output folder.
        options: :class:`OnlineOptions`.
        visualizer: receives frames and keyframes.
        stream: where pose events go (default: a new :class:`PoseStream` with
            ``options.jsonl``); read it from another thread, or start the pipeline with
            :meth:`start` and read it from this one.
    """

    def __init__(self, source: FrameSource, config: Config, out_dir: str | Path,
                 options: OnlineOptions | None = None, visualizer: NullVisualizer | None = None,
                 stream: PoseStream | None = None):
        super().__init__(source, config, out_dir, options or OnlineOptions(), visualizer)
        if LOOP_MODES[self.options.method] == "image_sift":
            raise ValueError("the online pipeline does not support gs-imagesift (it needs raw images per keyframe)")
        self.stream = stream or PoseStream(jsonl=self.options.jsonl)
        self.backend: BackendProcess | None = None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._outcome: RunResult | BaseException | None = None

    # ------------------------------------------------------------------ control
    def stop(self) -> None:
        """End the run after the current frame; everything so far is saved."""
        self._stop.set()

    def start(self) -> PoseStream:
        """Run in a background thread; returns :attr:`stream`. Stop with :meth:`stop`,
        collect the result with :meth:`join`."""
        if self._thread is not None:
            raise RuntimeError("the online pipeline was already started")

        def target():
            try:
                self._outcome = self.run()
            except BaseException as exc:
                self._outcome = exc

        self._thread = threading.Thread(target=target, name="tactile-slam-online", daemon=True)
        self._thread.start()
        return self.stream

    def join(self, timeout: float | None = None) -> RunResult:
        """Wait for a run begun with :meth:`start`; re-raises its error.

        Raises:
            TimeoutError: still running after ``timeout`` seconds.
        """
        if self._thread is None:
            raise RuntimeError("the online pipeline was not started")
        self._thread.join(timeout)
        if self._thread.is_alive():
            raise TimeoutError(f"the online pipeline is still running after {timeout} s")
        if isinstance(self._outcome, BaseException):
            raise self._outcome
        return self._outcome

    # ------------------------------------------------------------------ loop
    def run(self) -> RunResult:
        opts: OnlineOptions = self.options
        threads = torch.get_num_threads()
        if opts.tracker_threads is not None:
            torch.set_num_threads(opts.tracker_threads)
        try:
            return self._run(opts)
        finally:
            torch.set_num_threads(threads)
            self.stream.close()
            if self.backend is not None:
                self.backend.terminate()

    def _run(self, opts: OnlineOptions) -> RunResult:
        mode = LOOP_MODES[opts.method]
        if mode is not None:
            self._clear_outputs()  # the back end writes its files into the folder during the run
            self.backend = BackendProcess(self.config, mode, opts.skip_loops, self.out_dir,
                                          opts.preview_every_s, opts.backend_threads)
            self.backend.wait_ready(opts.start_timeout_s)
        kmap = KeyframeMap()
        feed = RealtimeFeed(self.source, opts.rate, opts.buffer_frames)
        arrival_of: dict[int, float] = {}
        indices, kf_of, kf_T, quality, keyframes = [], [], [], [], []
        t_geom, t_track, latency = [], [], []
        state = {"loops": 0, "corrected": False, "corrections": 0, "skipped": 0, "step_s": []}
        bar = tqdm(total=len(self.source) if hasattr(self.source, "__len__") else None,
                   disable=not opts.progress, unit="frame", desc="online")

        def batches():
            for a in feed:
                arrival_of[a.frame.index] = a.arrival
                yield collate([a.frame])
                if self._stop.is_set():
                    return

        def take(updates):
            for u in updates:
                kmap.apply(u)
                state["step_s"] += u.step_s
                state["skipped"] = u.skipped
                if u.loops > state["loops"]:
                    state["loops"], state["corrected"] = u.loops, True
                    state["corrections"] += 1

        def emit(kfs):
            for kf in kfs:
                packed = pack_keyframe(kf)
                kf = unpack_keyframe(packed)  # the pipeline keeps a view of the shared buffer
                kmap.add(kf)
                if self.backend is not None:
                    self.backend.send(packed)
                keyframes.append(kf)
                self.visualizer.on_keyframe(kf)

        stopped_by, error, interrupt = "end_of_stream", None, None
        tracker = None
        t_start = time.perf_counter()
        try:
            frames = batches()
            first = next(frames, None)
            if first is None:
                raise InputError(f"{self.source}: no frames to process")
            builder, pending = self._builder(first, frames)
            tracker = self._tracker()
            try:
                for batch in itertools.chain([pending] if pending is not None else [], frames):
                    if self.backend is not None:
                        take(self.backend.poll())
                    t0 = time.perf_counter()
                    frame = self._geometry(builder, batch)
                    t1 = time.perf_counter()
                    step = tracker.step(frame)
                    t2 = time.perf_counter()
                    t_geom.append(t1 - t0)
                    t_track.append(t2 - t1)
                    emit(step.keyframes)
                    # the frame's row before its event: a Ctrl+C while publishing (a callback, the JSON
                    # line) keeps the frame, which the tracker's final flush may make a keyframe
                    indices.append(step.index)
                    kf_of.append(step.keyframe_id if step.in_contact else -1)
                    kf_T.append(step.kf_T_frame.numpy() if step.kf_T_frame is not None else np.full((4, 4), np.nan))
                    quality.append((step.ccs, step.scr, step.conditioning))
                    self._publish(step, frame, kmap, state, feed, arrival_of, latency)
                    self.visualizer.on_frame(frame, step)
                    bar.update(1)
            finally:
                emit(tracker.finish())  # the session tail is saved however the stream ends
        except KeyboardInterrupt as exc:
            stopped_by, interrupt = "interrupted", exc
        except (InputError, ValueError, RuntimeError) as exc:
            stopped_by, error = "error", exc
        finally:
            feed.close()
            bar.close()
        if stopped_by == "end_of_stream" and self._stop.is_set():
            stopped_by = "stopped"
        final_stats = {}
        if self.backend is not None:
            take(self.backend.finish())
            if self.backend.final is not None:
                final_stats = self.backend.final[1]
        wall = time.perf_counter() - t_start
        if error is not None and not indices:
            raise error
        result = self._write(indices, kf_of, kf_T, quality, keyframes, kmap, t_geom, t_track, state["step_s"], wall,
                             error, tracker_counts(tracker))
        result.stats.update(final_stats)
        result.stats.update(self._online_stats(feed, latency, keyframes, state, stopped_by))
        # an interrupt while writing (the back end's files, the mesh) also leaves it unfinished
        result.stats["completed"] = result.stats["completed"] and stopped_by == "end_of_stream"
        if interrupt is not None:  # as offline; the outputs, mesh included, were written all the same
            result.stats["error"] = f"{type(interrupt).__name__}: {interrupt}"
        write_json(self.out_dir / "stats.json", result.stats)
        self.visualizer.close()
        if error is not None:
            raise error
        return result

    def _publish(self, step, frame: Frame, kmap: KeyframeMap, state: dict, feed: RealtimeFeed,
                 arrival_of: dict[int, float], latency: list[float]) -> None:
        event = PoseEvent(index=step.index, timestamp=float(frame.timestamp[0]), in_contact=step.in_contact,
                          frames_dropped=feed.dropped)
        if step.in_contact:
            map_T = kmap.start_T_kf[step.keyframe_id] @ step.kf_T_frame
            event.map_T_sensor, event.sensor_T_object = map_T, torch.linalg.inv(map_T)
            event.keyframe_id, event.session, event.group = step.keyframe_id, step.session, kmap.group[step.keyframe_id]
            event.is_keyframe, event.ccs, event.scr = step.is_keyframe, step.ccs, step.scr
            event.conditioning = step.conditioning
            event.loop_corrected, state["corrected"] = state["corrected"], False
        event.new_keyframes = [kf.video_index for kf in step.keyframes]
        arrived = arrival_of.pop(step.index, None)
        if arrived is not None:
            event.latency_ms = (feed.clock() - arrived) * 1000.0
            latency.append(event.latency_ms)
        self.stream.publish(event)

    def _online_stats(self, feed: RealtimeFeed, latency: list[float], keyframes: list, state: dict,
                      stopped_by: str) -> dict:
        lat = np.asarray(latency)
        skipped = state["skipped"]
        return {
            "online": True,
            "rate": self.options.rate,
            "frames_read": feed.stats.read,
            "frames_dropped": feed.dropped,
            "dropped_indices": list(feed.stats.dropped_indices),
            "frames_late": feed.stats.late,
            "latency_ms": {"median": float(np.median(lat)) if len(lat) else float("nan"),
                           "p95": float(np.percentile(lat, 95)) if len(lat) else float("nan"),
                           "max": float(lat.max()) if len(lat) else float("nan")},
            "keyframes_skipped_for_loops": skipped,
            "keyframes_skipped_fraction": skipped / len(keyframes) if keyframes else 0.0,
            "loop_corrections": state["corrections"],
            "pose_events": self.stream.published,
            "backend_error": self.backend.error if self.backend is not None else None,
            "stopped_by": stopped_by,
        }
