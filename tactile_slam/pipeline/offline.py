"""The offline pipeline: owns the data loop, progress, timing and the output folder.

``OfflinePipeline(source, config, out_dir, options).run()`` reads every frame, computes
geometry in batches, tracks frame by frame, builds the keyframe map and writes the
outputs described in :mod:`tactile_slam.pipeline.outputs`.
"""

from __future__ import annotations

import sys
import time
import warnings
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from tactile_slam.backend import BackEnd
from tactile_slam.calibration.model import GradientDecoder, ModelSensorWarning, load_model, model_sensor_mismatch
from tactile_slam.config import Config, resolve_device
from tactile_slam.eval.trajectory import write_tum
from tactile_slam.geometry.frame import Frame, FrameBuilder, InputError
from tactile_slam.io.dataset import FrameBatch, iter_batches
from tactile_slam.io.frames import FrameSource
from tactile_slam.io.scan import BackgroundCheck, BackgroundWarning, check_background, is_grey, mean_background
from tactile_slam.pipeline.odometry import OdometryMap
from tactile_slam.pipeline.outputs import (check_output_folder, clear_run_outputs, frame_poses, main_group,
                                          main_group_poses, write_frames_csv, write_json, write_pose_graph_png)
from tactile_slam.pipeline.visualizer import NullVisualizer
from tactile_slam.recon import ReconError, TriMesh, reconstruct
from tactile_slam.tracking.frame_to_frame import FrameToFrameTracker
from tactile_slam.tracking.keyframe import Keyframe
from tactile_slam.tracking.tracker import NormalFlowRegistrar, Tracker

# method -> loop-closure mode of the back end (None: no back end, odometry only)
LOOP_MODES = {
    "gelslam": "full",
    "gs-onlysift": "only_sift",
    "gs-onlynf": "only_nf",
    "gs-imagesift": "image_sift",
    "nf-kf": None,
    "nf": None,
}
METHODS = tuple(LOOP_MODES)


@dataclass
class RunOptions:
    """How to run.

    Attributes:
        method: ``"gelslam"`` (the full system: tracker, loop closure, pose graph),
            the ablations ``"gs-onlysift"``, ``"gs-onlynf"``, ``"gs-imagesift"``
            (method.md 9.5), ``"nf-kf"`` (the tracker alone) or ``"nf"``
            (frame-to-frame NormalFlow without keyframes: 5000 random samples, no checks).
        device: torch device for geometry and registration.
        model: calibration model path (default: the sensor's packaged model).
        batch_size: frames per geometry batch.
        progress: show a progress bar.
        mesh: reconstruct the main group (``mesh_fused.ply``, ``mesh.ply``,
            ``mesh.png``); ``False`` computes poses only.
    """

    method: str = "gelslam"
    device: str = "cpu"
    model: str | None = None
    batch_size: int = 8
    progress: bool = True
    mesh: bool = True


@dataclass
class RunResult:
    """What a run returns (and writes; docs/outputs.md).

    Attributes:
        poses: ``(T, 4, 4)`` each frame's sensor pose in the frame of the main group's
            first contact frame, metres (NaN rows: no pose), as ``poses.npy``.
        poses_by_group: ``(T, 4, 4)`` each frame's pose in its own group's first contact frame.
        frame_group: ``(T,)`` each frame's group (-1: none).
        keyframes: the keyframes in insertion order (their maps cropped to the contact).
        stats: ``stats.json``.
        start_T_kf: keyframe id -> ``(4, 4)`` float64 pose of the keyframe in its group's
            start frame, metres (what :func:`~tactile_slam.recon.reconstruct` takes).
        keyframe_group: keyframe id -> its group.
    """

    poses: np.ndarray
    poses_by_group: np.ndarray
    frame_group: np.ndarray
    keyframes: list[Keyframe]
    stats: dict = field(default_factory=dict)
    start_T_kf: dict[int, torch.Tensor] = field(default_factory=dict)
    keyframe_group: dict[int, int] = field(default_factory=dict)


def tracker_counts(tracker) -> dict:
    """The tracker's counters for ``stats.json`` (0 for trackers without them, e.g. the
    frame-to-frame baselines)."""
    return {"implausible_motions": getattr(tracker, "implausible", 0),
            "moved_keyframe_edges": getattr(tracker, "moved_edges", 0),
            "kept_keyframe_edges": getattr(tracker, "kept_edges", 0),
            "coarse_rescues": getattr(tracker, "coarse_rescues", 0),
            "registration_breaks": getattr(tracker, "registration_breaks", 0),
            "tilted_registrations": getattr(tracker, "tilted", 0),
            "f2f_checks": getattr(tracker, "f2f_checks", 0),
            "f2f_refusals": getattr(tracker, "f2f_refusals", 0)}


class OfflinePipeline:
    """Args:
        source: frames (a recording or a stream).
        config: settings; written back resolved to ``config.yaml``.
        out_dir: output folder (checked here, before any work; created when the first
            result is written).
        options: method, device, batching.
        visualizer: receives frames and keyframes; :class:`NullVisualizer` by default.
    """

    def __init__(self, source: FrameSource, config: Config, out_dir: str | Path,
                 options: RunOptions | None = None, visualizer: NullVisualizer | None = None):
        config.validate()  # a Config changed in Python skips the YAML loader's checks
        config.check_factors()  # tracking's block-averaged levels need a size they divide
        self.source = source
        self.config = config
        self.out_dir = check_output_folder(out_dir)
        self.options = options or RunOptions()
        if self.options.method not in METHODS:
            raise ValueError(f"method must be one of {METHODS}, got {self.options.method!r}")
        self.options = replace(self.options, device=resolve_device(self.options.device))
        self.visualizer = visualizer or NullVisualizer()
        self._outputs_cleared = False
        self._window_check: BackgroundCheck | None = None  # of a stream's background window
        self._model: str | None = None  # the calibration model images were decoded with

    def _clear_outputs(self) -> None:
        """Remove an earlier run's outputs from the output folder (:func:`clear_run_outputs`),
        once per run, before this run writes its first one."""
        if self._outputs_cleared:
            return
        self._outputs_cleared = True
        stale = clear_run_outputs(self.out_dir) if self.out_dir.is_dir() else []
        if stale:
            print(f"{self.out_dir}: replaced the outputs of an earlier run ({', '.join(stale)})", file=sys.stderr)

    # ------------------------------------------------------------------ set-up
    def _builder(self, first: FrameBatch, frames) -> tuple[FrameBuilder, FrameBatch | None]:
        """A frame builder, and the first batch still to process. For image input
        without a known background, the first ``background_frames`` frames of the
        stream become the background and are not tracked."""
        if first.bgr is None:
            return FrameBuilder(self.config, device=self.options.device), first
        background = getattr(self.source, "background", None)
        rest = first
        if background is None:
            n = self.config.sensor.background_frames
            window, rest = [first], first
            while sum(len(b) for b in window) < n:
                nxt = next(frames, None)
                if nxt is None:
                    raise InputError(f"{self.source}: fewer frames than the {n}-frame background window")
                window.append(nxt)
            stack = torch.cat([b.bgr for b in window]).numpy()
            background = mean_background(stack[:n])
            self._window_check = check_background(stack[:n]) if n >= 2 else None
            if self._window_check is not None and not self._window_check.ok:
                warnings.warn(f"{self.source}: the background frames differ; was the gel touched?", stacklevel=2)
            used = n - sum(len(b) for b in window[:-1])
            rest = window[-1]._map(lambda x: x[used:]) if used < len(window[-1]) else None
        if is_grey(background):
            warnings.warn(f"{self.source}: the frames are greyscale (B = G = R); the calibration model decodes the "
                          "sensor's colour lighting, so their gradients and poses will be wrong", BackgroundWarning,
                          stacklevel=2)
        path = self.options.model or self.config.sensor.resolved_model_path()
        if path is None:
            raise InputError(
                f"no calibration model for sensor {self.config.sensor.name!r}: pass --model or set sensor.model_path"
            )
        model, meta = load_model(path, self.options.device)
        self._model = str(Path(path).resolve())
        if self.options.model:  # config.yaml then names it, so --config config.yaml repeats the run
            self.config = replace(self.config, sensor=replace(self.config.sensor, model_path=self._model))
        mismatch = model_sensor_mismatch(meta, self.config.sensor)
        if mismatch is not None:
            warnings.warn(f"{path}: {mismatch}; its gradients will be wrong (calibrate this sensor: "
                          "tactile-slam calibrate)", ModelSensorWarning, stacklevel=2)
        bg = torch.as_tensor(np.asarray(background), dtype=torch.float32)
        decoder = GradientDecoder(model, bg, self.config.contact.mlp_skip_color_dist)
        return FrameBuilder(self.config, decoder), rest

    def _tracker(self):
        if self.options.method == "nf":  # the public NormalFlow tracker: none of our sample rules
            nf = replace(self.config.normalflow, n_samples=5000, selection="random", check_scores=False,
                         decoded_max_slope=None, max_slope=None)
            return FrameToFrameTracker(NormalFlowRegistrar(nf, self.config.tracking),
                                       self.config.tracking.keep_contact_mm2)
        return Tracker(self.config.tracking, NormalFlowRegistrar(self.config.normalflow, self.config.tracking))

    # ------------------------------------------------------------------ loop
    def run(self) -> RunResult:
        opts = self.options
        frames = iter_batches(iter(self.source), opts.batch_size)
        first = next(frames, None)
        if first is None:
            raise InputError(f"{self.source}: no frames to process")
        builder, pending = self._builder(first, frames)
        tracker = self._tracker()
        mode = LOOP_MODES[opts.method]
        backend = BackEnd(self.config, mode) if mode is not None else OdometryMap()
        images: dict[int, torch.Tensor] = {}  # recent raw images, for image-SIFT keyframes
        indices, kf_of, kf_T, quality = [], [], [], []
        keyframes: list[Keyframe] = []
        t_geom, t_track, t_back = [], [], []
        n_total = len(self.source) if hasattr(self.source, "__len__") else None
        bar = tqdm(total=n_total, disable=not opts.progress, unit="frame", desc="tracking")
        t_start = time.perf_counter()
        error: BaseException | None = None

        def emit(kfs):
            for kf in kfs:
                if mode == "image_sift":
                    image = images.get(kf.video_index)
                    kf.image = None if image is None else image.clone()  # not a view pinning the batch
                t0 = time.perf_counter()
                backend.add(kf)
                t_back.append(time.perf_counter() - t0)
                keyframes.append(kf)
                self.visualizer.on_keyframe(kf)
                kf.compact()  # from here on it is an earlier keyframe: its maps around the contact

        try:
            batches = ([pending] if pending is not None else [])
            for batch in _chain(batches, frames):
                t0 = time.perf_counter()
                fr = self._geometry(builder, batch)
                t_geom.extend([(time.perf_counter() - t0) / len(batch)] * len(batch))
                for i in range(len(fr)):
                    one = fr[i]
                    if mode == "image_sift":
                        images = {k: v for k, v in images.items() if k >= int(batch.index[i]) - 2}
                        images[int(batch.index[i])] = batch.bgr[i].cpu() if batch.bgr is not None else None
                    t0 = time.perf_counter()
                    step = tracker.step(one)
                    t_track.append(time.perf_counter() - t0)
                    emit(step.keyframes)
                    indices.append(step.index)
                    kf_of.append(step.keyframe_id if step.in_contact else -1)
                    kf_T.append(step.kf_T_frame.numpy() if step.kf_T_frame is not None else np.full((4, 4), np.nan))
                    quality.append((step.ccs, step.scr, step.conditioning))
                    self.visualizer.on_frame(one, step)
                bar.update(len(batch))
            emit(tracker.finish())
        except KeyboardInterrupt as exc:  # keep what was computed
            error = exc
        except (InputError, ValueError, RuntimeError) as exc:
            error = exc
        finally:
            bar.close()
        wall = time.perf_counter() - t_start
        try:
            backend.finish()
        except KeyboardInterrupt as exc:  # the graph as the last keyframe left it
            error = error or exc
        result = self._write(indices, kf_of, kf_T, quality, keyframes, backend, t_geom, t_track, t_back, wall,
                             error, tracker_counts(tracker))
        self.visualizer.close()
        if error is not None and not isinstance(error, KeyboardInterrupt):
            raise error
        return result

    def _geometry(self, builder: FrameBuilder, batch: FrameBatch) -> Frame:
        batch = batch.to(self.options.device)
        if batch.bgr is not None:
            return builder.from_bgr(batch.bgr, batch.index, batch.timestamp)
        return builder.from_gradients(batch.gradients, batch.contact, batch.index, batch.timestamp)

    # ------------------------------------------------------------------ outputs
    def _write(self, indices, kf_of, kf_T, quality, keyframes, backend, t_geom, t_track, t_back, wall, error,
               counts: dict) -> RunResult:
        out = self.out_dir
        n = len(indices)
        contact_frames = sum(1 for k in kf_of if k >= 0)
        if n == 0 and error is not None:  # stopped before the first frame: nothing to write
            raise error
        if n and contact_frames == 0 and error is None:
            check = getattr(self.source, "background_check", None) or self._window_check
            touched = check is not None and not check.ok
            hint = (f"; the first {self.config.sensor.background_frames} frames, taken as the background, differ: "
                    "if the gel was touched from the start, give the recording a background.png") if touched else ""
            raise InputError(f"{self.source}: no frame of {n} is in contact: nothing to track{hint}")
        self._clear_outputs()
        out.mkdir(parents=True, exist_ok=True)
        # poses are indexed by video index: rows for skipped frames (background window) stay NaN
        t = (max(indices) + 1) if indices else 0
        kf_of_full = np.full(t, -1, dtype=np.int64)
        kf_T_full = np.full((t, 4, 4), np.nan)
        quality_full = np.full((t, 3), np.nan)
        if n:
            idx = np.asarray(indices)
            kf_of_full[idx] = kf_of
            kf_T_full[idx] = np.stack(kf_T)
            quality_full[idx] = np.asarray(quality, dtype=np.float64)
        start_T_kf, group_of_kf = dict(backend.start_T_kf), dict(backend.group)  # snapshots of live views
        by_group, groups = frame_poses(kf_of_full, kf_T_full, start_T_kf, group_of_kf)
        poses = main_group_poses(by_group, groups)
        fps = float(getattr(self.source, "fps", self.config.sensor.fps) or self.config.sensor.fps)
        np.save(out / "poses.npy", poses)
        np.save(out / "poses_by_group.npy", by_group)
        np.save(out / "frame_group.npy", groups)
        write_tum(out / "trajectory_tum.txt", np.arange(t) / fps, poses)
        write_frames_csv(out / "frames.csv", fps, groups, kf_of_full, {k.id: k.session for k in keyframes},
                         {k.video_index for k in keyframes}, quality_full)
        write_json(out / "keyframes.json", [
            {"id": k.id, "video_index": k.video_index, "session": k.session, "group": group_of_kf[k.id],
             "new_session": k.new_session, "depth_known": k.depth_known, "pose": start_T_kf[k.id].tolist()}
            for k in keyframes
        ])
        med = lambda xs: float(np.median(xs) * 1000) if xs else float("nan")  # noqa: E731
        name = str(getattr(self.source, "name", self.source))
        stats = {
            "source": str(Path(name).resolve()) if Path(name).exists() else name,  # what eval checks the run against
            "model": self._model,
            "method": self.options.method,
            "device": self.options.device,
            "frames": n,
            "contact_frames": contact_frames,
            "frames_with_pose": int(np.isfinite(poses).all(axis=(1, 2)).sum()),
            "keyframes": len(keyframes),
            "keyframes_depth_unknown": sum(not k.depth_known for k in keyframes),
            "sessions": len({k.session for k in keyframes}),
            "groups": len(set(group_of_kf.values())),
            **counts,
            "fps": n / wall if wall > 0 else float("nan"),
            "wall_time_s": wall,
            "timing_ms": {"geometry": med(t_geom), "tracking": med(t_track),
                          "total": med([a + b for a, b in zip(t_geom, t_track)]),
                          "backend_per_keyframe": med(t_back)},
            "completed": error is None,
        }
        try:  # an interrupt here still leaves stats.json beside the poses
            if isinstance(backend, BackEnd):
                stats.update(self._write_backend(backend))
            if self.options.mesh and error is None:
                stats["reconstruction"] = self._reconstruct(keyframes, start_T_kf, group_of_kf, kf_of_full,
                                                            kf_T_full, groups)
        except KeyboardInterrupt as exc:
            error = exc
            stats["completed"] = False
        if error is not None:
            stats["error"] = f"{type(error).__name__}: {error}"
        write_json(out / "stats.json", stats)
        self.config.save(out / "config.yaml")
        return RunResult(poses, by_group, groups, keyframes, stats, start_T_kf, group_of_kf)

    def _reconstruct(self, keyframes, start_T_kf, group_of_kf, kf_of, kf_T, frame_group) -> dict:
        """Mesh of the main group in the frame of its first contact frame (the frame of
        ``poses.npy``); with ``recon.all_groups`` also every other group, in the frame of
        its own first contact frame (that of ``poses_by_group.npy``), under
        ``groups/group_<label>/`` (no rendering). A group that cannot be meshed says why
        in ``stats.json``."""

        def mesh_group(label: int, out_dir: Path, render: bool) -> dict:
            first = int(np.nonzero(frame_group == label)[0][0])
            try:
                res = reconstruct(keyframes, start_T_kf, self.config, group_of_kf, group=label)
            except ReconError as exc:
                print(f"reconstruction of group {label} skipped: {exc}")
                return {"skipped": str(exc)}
            first_T_start = torch.linalg.inv(start_T_kf[int(kf_of[first])] @ torch.as_tensor(kf_T[first]))
            res.fused_mesh = transform_mesh(res.fused_mesh, first_T_start)
            if res.mesh is not None:
                res.mesh = transform_mesh(res.mesh, first_T_start)
            out_dir.mkdir(parents=True, exist_ok=True)
            res.save(out_dir, render=render)
            return {k: v for k, v in res.stats.items() if isinstance(v, (int, float, str, bool))}

        label = main_group(frame_group)
        stats = mesh_group(label, self.out_dir, True)
        if self.config.recon.all_groups:
            others = [int(g) for g in np.unique(frame_group[frame_group >= 0]) if g != label]
            stats["other_groups"] = {str(g): mesh_group(g, self.out_dir / "groups" / f"group_{g}", False)
                                     for g in others}
        return stats

    def _write_backend(self, backend: BackEnd) -> dict:
        """``loops.json``, ``loops_held.json``, ``pose_graph.g2o``, ``pose_graph.png`` and the back end's statistics."""
        backend.write(self.out_dir)
        if backend.graph.num_nodes:
            write_pose_graph_png(self.out_dir / "pose_graph.png", backend)
        return backend.summary()


def transform_mesh(mesh: TriMesh, a_T_b: torch.Tensor) -> TriMesh:
    """A mesh in frame b moved into frame a (vertices and normals)."""
    T = a_T_b.to(mesh.vertices)
    return replace(mesh, vertices=mesh.vertices @ T[:3, :3].T + T[:3, 3], normals=mesh.normals @ T[:3, :3].T)


def _chain(first: list, rest):
    yield from first
    yield from rest
