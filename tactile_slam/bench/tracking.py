"""Tracking accuracy (Table IV layout): NF, NF-KF, ICP, FPFH+RI, GelSLAM variants on simulated episodes.

Episodes come from :func:`tactile_slam.sim.episode.simulate_episode` and are cached in
``--cache`` (a rerun with the same settings skips simulation). Three episode sets:

* ``tracking/gradients``: continuous-contact episodes of ``--objects`` x ``--seeds``,
  ground-truth gradients and contact masks as input, every method of ``--methods``;
* ``tracking/image``: the same motion of ``--image-objects`` (first seed) rendered to
  GelSight images through the shipped colour model and decoded by the shipped
  calibration MLP; ``--image-methods`` (GS-ImageSIFT needs the raw image);
* ``contact_loss/gradients``: the paper's contact-loss protocol (frames with
  ``(i - lead_in) mod 100 >= 75`` lifted) for ``--loss-objects`` (first seed),
  ``--loss-methods``; scored on the retained (in-contact) frames.

Methods (method.md 9.5): the pipeline's ``nf`` (frame-to-frame NormalFlow, 5000 random
samples, no checks, no keyframes), ``nf-kf`` (the tracker alone), ``gelslam``
(GS-Offline), ``gs-onlysift``, ``gs-onlynf``, ``gs-imagesift``; and the point-cloud
baselines ``icp`` and ``fpfh`` (FPFH+RANSAC+ICP) run the same way as NF: each
in-contact frame is registered against the previous in-contact frame from the identity,
the estimates are composed, and a failed registration (error or fewer inliers than the
baseline's minimum) keeps the previous pose. The baselines run on the gradient-level tracking set only.

Scoring (method.md 9.1): every trajectory is expressed in the sensor frame of its first
frame with a pose (the first contact frame of the main group), the ground truth
likewise; per-axis absolute errors of NormalFlow's ``zxy`` Euler convention over the
frames after it that the ground truth has in contact and the method estimates. Per
object the errors are pooled over all frames of all seeds (NormalFlow's pooling); the
summary row is the plain mean of the per-object pooled MAEs over the objects not in
``EXCLUDED_FROM_MEAN`` (ball, cylinder: the paper's exclusion). Loops (``loops.json``)
are scored against the ground-truth relative pose (correct within 0.3 mm and 1 degree;
loops from video within their declared tilt sigma out of plane, :mod:`tactile_slam.eval.loop_metrics`;
``correct_full_pose`` counts by 1 degree alone);
recall is over the ground-truth loops among the run's keyframes (pairs >= 25 frames
apart whose true contact patches overlap by >= 5 mm^2). Times are per-episode medians
(ms per frame per stage, ms per keyframe for the back end), then the median over
episodes.

Methods that merge sessions (GS-Offline) estimate frames the tracker alone leaves
unposed, from another reference frame, so their pooled MAE is over a longer and harder
motion. Each row therefore also has ``objects_shared_frames``: the same per-object MAE
on the frames that every method of the episode estimates, all relative to the first of
them (:func:`shared_frame_errors`).

The JSON's ``results.runs`` lists each command that contributed (settings, date,
machine, tables, wall time): with ``--append`` a command adds its tables to the report at
``--out`` instead of replacing it, so several commands with different settings (the
gradient set at 500 frames, the image set, the contact-loss set) make one report.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import tempfile
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import torch

from tactile_slam.bench.common import machine_info, median_per_key, set_threads, write_json
from tactile_slam.cli.arguments import positive_int
from tactile_slam.cli.eval import evaluate_run
from tactile_slam.config import Config, load_config
from tactile_slam.eval.loop_metrics import gt_loop_pairs, loop_flags, loop_precision_recall
from tactile_slam.eval.tracking_metrics import AXES, per_axis_errors
from tactile_slam.eval.trajectory import relative_to, valid_mask
from tactile_slam.geometry.frame import FrameBuilder
from tactile_slam.registration.baselines import register_fpfh, register_icp
from tactile_slam.registration.result import RegistrationError

PIPELINE_METHODS = ("nf", "nf-kf", "gelslam", "gs-onlysift", "gs-onlynf", "gs-imagesift")
BASELINES = {"icp": register_icp, "fpfh": register_fpfh}
LABELS = {"nf": "NF", "nf-kf": "NF-KF", "icp": "ICP", "fpfh": "FPFH+RI", "gelslam": "GS-Offline",
          "gs-onlysift": "GS-OnlySIFT", "gs-onlynf": "GS-OnlyNF", "gs-imagesift": "GS-ImageSIFT"}
LOOP_METHODS = ("gelslam", "gs-onlysift", "gs-onlynf", "gs-imagesift")
EXCLUDED_FROM_MEAN = ("ball", "cylinder")
LOW_TEXTURE = ("handle", "ball", "plane")  # not "textured" for the targets
ROT, TRANS = AXES[3:], AXES[:3]


class BenchConfigError(ValueError):
    """The benchmark's episode set or method list is invalid."""


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--objects", nargs="+", default=["seed", "shell", "dice", "lime", "handle", "knurled"])
    p.add_argument("--seeds", nargs="+", type=int, default=[0, 1])
    p.add_argument("--frames", type=positive_int, default=200, help="frames per tracking episode (10 lead-in)")
    p.add_argument("--methods", nargs="+",
                   default=["nf", "nf-kf", "icp", "gelslam", "gs-onlysift", "gs-onlynf"],
                   help="methods on the gradient-level tracking set (add fpfh: seconds per frame)")
    p.add_argument("--level", choices=["gradients", "image", "both"], default="both",
                   help="input level of the tracking set (image: --image-objects, first seed)")
    p.add_argument("--image-objects", nargs="+", default=["seed", "shell"])
    p.add_argument("--image-methods", nargs="+", default=["gelslam", "gs-imagesift"])
    p.add_argument("--protocol", choices=["tracking", "contact_loss", "both"], default="both")
    p.add_argument("--loss-objects", nargs="+", default=["seed", "shell", "knurled"])
    p.add_argument("--loss-frames", type=positive_int, default=310, help="frames per contact-loss episode")
    p.add_argument("--loss-methods", nargs="+", default=["nf", "nf-kf", "gelslam"])
    p.add_argument("--cache", default="outputs/bench_tracking_episodes", help="episode cache folder")
    p.add_argument("--work", default=None, help="run output folder (default: a temporary folder)")
    p.add_argument("--threads", type=positive_int, default=None, help="torch CPU threads")
    p.add_argument("--config", default=None,
                   help="YAML config or preset for the runs (default: GelSight Mini); the episodes are simulated "
                        "with the default sensor")
    p.add_argument("--png", default=None, help="plot path (default: the JSON path with .png)")
    p.add_argument("--append", action="store_true",
                   help="merge this run into the JSON at --out: its tables and episodes replace those of the "
                        "same name, the others stay, and the targets are recomputed (several commands, one report)")


@dataclass(frozen=True)
class EpisodeSpec:
    """One simulated episode and the methods to run on it."""

    object: str
    seed: int
    kind: str
    level: str
    frames: int
    methods: tuple[str, ...]
    digest: str | None = None  # of a mesh file's bytes (episode_specs sets it)

    @property
    def label(self) -> str:
        """The object's name in the report: a catalogue name, or a mesh file's name."""
        return object_label(self.object)

    @property
    def name(self) -> str:
        """Episode folder and report name; a mesh file's adds a digest of its bytes, so an
        edited mesh is simulated again instead of read from the cache."""
        obj = self.label if self.digest is None else f"{self.label}-{self.digest}"
        return f"{self.kind}_{self.level}_{obj}_s{self.seed}_f{self.frames}"

    @property
    def table(self) -> str:
        return f"{self.kind}/{self.level}"


def object_label(obj: str) -> str:
    """``obj`` if it is a catalogue object, else the mesh file's name (``torus.ply``)."""
    from tactile_slam.sim.objects import OBJECTS

    return obj if obj in OBJECTS else Path(obj).name


def episode_specs(args) -> list[EpisodeSpec]:
    """The episode set the flags describe (see the module docstring)."""
    known = set(PIPELINE_METHODS) | set(BASELINES)
    for flag in ("methods", "image_methods", "loss_methods"):
        bad = [m for m in getattr(args, flag) if m not in known]
        if bad:
            raise BenchConfigError(f"--{flag.replace('_', '-')}: unknown methods {bad}; choose from {sorted(known)}")
    if "gs-imagesift" in args.methods:
        raise BenchConfigError("gs-imagesift needs image input: list it in --image-methods, not --methods")
    specs = []
    if args.protocol in ("tracking", "both"):
        if args.level in ("gradients", "both"):
            specs += [EpisodeSpec(o, s, "tracking", "gradients", args.frames, tuple(args.methods))
                      for o in args.objects for s in args.seeds]
        if args.level in ("image", "both"):  # the baselines would read the true gradients: not run here
            image = tuple(m for m in args.image_methods if m not in BASELINES)
            specs += [EpisodeSpec(o, args.seeds[0], "tracking", "image", args.frames, image)
                      for o in args.image_objects]
    if args.protocol in ("contact_loss", "both"):
        loss = tuple(m for m in args.loss_methods if m not in BASELINES and m != "gs-imagesift")
        specs += [EpisodeSpec(o, args.seeds[0], "contact_loss", "gradients", args.loss_frames, loss)
                  for o in args.loss_objects]
    specs = [s for s in specs if s.methods]
    if not specs:
        raise BenchConfigError("the flags select no episode")
    from tactile_slam.sim.objects import OBJECTS

    missing = sorted({s.object for s in specs if s.object not in OBJECTS and not Path(s.object).is_file()})
    if missing:
        raise BenchConfigError(f"unknown objects {missing}: give catalogue names {sorted(OBJECTS)} or mesh files")
    digests = {o: hashlib.sha1(Path(o).read_bytes()).hexdigest()[:10] for o in {s.object for s in specs}
               if o not in OBJECTS}
    specs = [replace(s, digest=digests.get(s.object)) for s in specs]
    labels: dict[str, str] = {}
    for s in specs:
        if labels.setdefault(s.label, s.object) != s.object:
            raise BenchConfigError(f"objects {labels[s.label]!r} and {s.object!r} share the report name {s.label!r}")
    return specs


# ------------------------------------------------------------------ episodes


def cached_episode(cache: Path, spec: EpisodeSpec, config: Config) -> Path:
    """The episode folder of ``spec`` under ``cache``, simulated when missing, made by an
    earlier motion revision or, at the image level, composed on another background than the
    one found now (the real one appeared or went away)."""
    from tactile_slam.sim.episode import (EpisodeError, SimulationSettings, background_source, read_episode,
                                          simulate_episode)
    from tactile_slam.sim.motions import MOTION_REVISION

    path = cache / spec.name
    done = path / "meta.yaml"
    if done.is_file():
        try:
            ep = read_episode(path)
            if len(ep) == spec.frames and ep.meta.get("level") == spec.level \
                    and ep.meta.get("motion_revision") == MOTION_REVISION \
                    and (spec.level != "image" or ep.background == background_source()):
                return path
        except EpisodeError:
            pass
    settings = SimulationSettings(object=spec.object, kind=spec.kind, seed=spec.seed, frames=spec.frames,
                                  level=spec.level)
    return simulate_episode(path, settings, config)


# ------------------------------------------------------------------ methods


def baseline_poses(episode_dir: Path, method: str, config: Config, batch: int = 16) -> tuple[np.ndarray, dict]:
    """Frame-to-frame ICP / FPFH+RANSAC+ICP over an episode's ground-truth gradients.

    Returns:
        ``(start_T_curr (T, 4, 4) float64 metres, NaN rows for frames out of contact;
        the start is the first in-contact frame; timing {"geometry", "registration"} ms
        per frame medians)``.
    """
    from tactile_slam.sim.episode import read_episode

    grads, contact = read_episode(episode_dir).gradients()
    builder = FrameBuilder(config)
    register = BASELINES[method]
    poses = np.full((len(grads), 4, 4), np.nan)
    t_geom, t_reg = [], []
    prev, start_T_prev = None, np.eye(4)
    for a in range(0, len(grads), batch):
        t0 = time.perf_counter()
        frames = builder.from_gradients(torch.from_numpy(grads[a:a + batch].astype(np.float32)),
                                        torch.from_numpy(contact[a:a + batch]))
        t_geom += [(time.perf_counter() - t0) / len(frames)] * len(frames)
        for k in range(len(frames)):
            cur = frames[k]
            if not bool(cur.in_contact[0]):
                continue
            if prev is not None:
                t0 = time.perf_counter()
                try:
                    res = register(prev, cur)
                    if bool(res.ok[0]):
                        start_T_prev = start_T_prev @ np.linalg.inv(res.tar_T_ref[0].double().cpu().numpy())
                except RegistrationError:
                    pass  # keep the previous pose
                t_reg.append(time.perf_counter() - t0)
            poses[a + k] = start_T_prev
            prev = cur
    med = lambda xs: float(np.median(xs) * 1000) if xs else float("nan")  # noqa: E731
    return poses, {"geometry": med(t_geom), "registration": med(t_reg)}


def loop_scores(run_dir: Path, episode_dir: Path, config: Config) -> dict:
    """Precision/recall of the run's ``loops.json`` against the ground truth, with
    the ground-truth loops among the run's keyframes (:func:`gt_loop_pairs`)."""
    from tactile_slam.sim.episode import read_episode

    ep = read_episode(episode_dir)
    kfs = json.loads((run_dir / "keyframes.json").read_text())
    video = {k["id"]: k["video_index"] for k in kfs}
    loops_path = run_dir / "loops.json"
    loops = json.loads(loops_path.read_text()) if loops_path.is_file() else []
    pairs = np.array([[video[lp["ref_id"]], video[lp["tar_id"]]] for lp in loops], dtype=np.int64).reshape(-1, 2)
    ref_T_tar = np.array([lp["ref_T_tar"] for lp in loops], dtype=np.float64).reshape(-1, 4, 4)
    cand = np.unique(np.fromiter(video.values(), dtype=np.int64))
    grads, contact = ep.gradients()
    physical = replace(config, contact=replace(config.contact, given_masks="final"))  # truth: the simulator's contact
    frames = FrameBuilder(physical).from_gradients(torch.from_numpy(grads[cand].astype(np.float32)),
                                                   torch.from_numpy(contact[cand]))
    h, w = config.sensor.shape
    height = np.zeros((len(ep), h, w), np.float32)
    mask = np.zeros((len(ep), h, w), bool)
    height[cand], mask[cand] = frames.height.cpu().numpy(), frames.contact.cpu().numpy()
    gt = gt_loop_pairs(cand, ep.object_T_sensor, height, mask, config.sensor.mm_per_px)
    known, sigma = loop_flags(loops)
    out = loop_precision_recall(pairs, ref_T_tar, ep.object_T_sensor, gt, depth_known=known, tilt_sigma_deg=sigma)
    out["false"] = out["reported"] - out["correct"]
    return out


def run_method(episode_dir: Path, method: str, run_dir: Path, config: Config) -> dict:
    """Run one method on one episode and score it; also returns the per-frame errors."""
    from tactile_slam.io.dispatch import open_source
    from tactile_slam.pipeline.offline import OfflinePipeline, RunOptions

    t0 = time.perf_counter()
    if method in BASELINES:
        poses, timing = baseline_poses(episode_dir, method, config)
        run_dir.mkdir(parents=True, exist_ok=True)
        np.save(run_dir / "poses.npy", poses)
        stats = {"timing_ms": {**timing, "total": timing["geometry"] + timing["registration"]}}
    else:
        source = open_source(episode_dir, config)
        res = OfflinePipeline(source, config, run_dir, RunOptions(method=method, mesh=False, progress=False)).run()
        stats = res.stats
    wall = time.perf_counter() - t0
    metrics, series = evaluate_run(run_dir, episode_dir, recon=False)
    tr = metrics["tracking"]
    out = {
        "per_axis_mae": tr["per_axis_mae"], "ate": tr["ate"], "rpe_1": tr["rpe_1"],
        "estimated_fraction": tr["estimated_fraction"], "reference_frame": metrics["reference_frame"],
        "wall_s": wall, "timing_ms": stats.get("timing_ms", {}),
    }
    for key in ("keyframes", "sessions", "groups", "loops", "loop_candidates", "coverage_keyframes",
                "timing_ms_per_keyframe"):
        if key in stats:
            out[key] = stats[key]
    if method in LOOP_METHODS:
        out["loop_eval"] = loop_scores(run_dir, episode_dir, config)
    errors = series["errors"][1:]  # the reference frame is the start: skipped, as in per_axis_mae
    return out, errors[np.isfinite(errors).all(axis=1)]


def shared_frame_errors(poses: dict[str, np.ndarray], object_T_sensor: np.ndarray,
                        in_contact: np.ndarray) -> tuple[int | None, dict[str, np.ndarray]]:
    """Per-axis errors of several runs of one episode on the frames that **every** run
    estimates, all taken relative to the first of them, so that methods that estimate
    different frames (a method that merges sessions estimates more, and from another
    reference) are compared on the same motion.

    Args:
        poses: method -> ``(T, 4, 4)`` ``start_T_frame`` (``poses.npy``, NaN rows unestimated).
        object_T_sensor: ``(T, 4, 4)`` ground truth.
        in_contact: ``(T,)`` bool, the frames scored.

    Returns:
        ``(reference frame or None when no frame is shared, method -> (N, 6) errors
        [x, y, z mm, rx, ry, rz deg] over the shared frames after the reference)``.
    """
    use = np.asarray(in_contact, dtype=bool).copy()
    for p in poses.values():
        use &= valid_mask(p)
    if not use.any():
        return None, {m: np.zeros((0, 6)) for m in poses}
    ref = int(np.argmax(use))
    use[ref] = False
    gt = relative_to(object_T_sensor, ref)
    return ref, {m: per_axis_errors(relative_to(p, ref), gt)[use] for m, p in poses.items()}


# ------------------------------------------------------------------ aggregation


def _mae(errors: list[np.ndarray]) -> dict:
    e = np.concatenate(errors) if errors else np.zeros((0, 6))
    out = {k: float(e[:, i].mean()) if len(e) else float("nan") for i, k in enumerate(AXES)}
    out["rot_deg"] = float(np.mean([out[k] for k in ROT]))
    out["trans_mm"] = float(np.mean([out[k] for k in TRANS]))
    out["n_frames"] = int(len(e))
    return out


def summarise(episodes: list[dict], errors: dict, shared: dict | None = None) -> dict:
    """Per table, per method: per-object pooled MAE, the mean over objects (ball and
    cylinder excluded), loop totals and median stage times; with ``shared`` (the errors
    of :func:`shared_frame_errors`, keyed like ``errors``) also the per-object MAE on the
    frames every method of an episode estimates (``objects_shared_frames``)."""
    tables: dict = {}
    for ep in episodes:
        for m in ep["methods"]:
            tables.setdefault(ep["table"], {}).setdefault(m, {}).setdefault(ep["object"], []).append(ep)
    out = {}
    for table, methods in tables.items():
        out[table] = {}
        for m, per_obj in methods.items():
            objs = {o: _mae(errors[(table, m, o)]) for o in per_obj}
            kept = [o for o in objs if o not in EXCLUDED_FROM_MEAN and objs[o]["n_frames"]]
            mean = {k: float(np.mean([objs[o][k] for o in kept])) if kept else float("nan")
                    for k in (*AXES, "rot_deg", "trans_mm")}
            eps = [e["methods"][m] for obj_eps in per_obj.values() for e in obj_eps]
            row = {"label": LABELS[m], "objects": objs, "mean_over_objects": mean, "mean_objects": kept,
                   "estimated_fraction": float(np.mean([e["estimated_fraction"] for e in eps])),
                   "timing_ms_median": median_per_key([e["timing_ms"] for e in eps])}
            if shared is not None:
                row["objects_shared_frames"] = {o: _mae(shared.get((table, m, o), [])) for o in per_obj}
            if any("keyframes" in e for e in eps):
                row["keyframes_mean"] = float(np.mean([e.get("keyframes", 0) for e in eps]))
                row["sessions_mean"] = float(np.mean([e.get("sessions", 0) for e in eps]))
            if m in LOOP_METHODS:
                le = [e["loop_eval"] for e in eps]
                rep, cor = sum(x["reported"] for x in le), sum(x["correct"] for x in le)
                full = sum(x["correct_full_pose"] for x in le)
                gt, found = sum(x["gt_loops"] for x in le), sum(x["found"] for x in le)
                row["loops"] = {"reported": rep, "correct": cor, "false": rep - cor, "correct_full_pose": full,
                                "precision": cor / rep if rep else float("nan"),
                                "gt_loops": gt, "found": found, "recall": found / gt if gt else float("nan"),
                                "episodes_with_false_loops": sum(x["false"] > 0 for x in le)}
                row["timing_ms_per_keyframe_median"] = median_per_key(
                    [e.get("timing_ms_per_keyframe", {}) for e in eps])
            out[table][m] = row
    return out


BEATS_MARGIN = 1e-9  # smallest relative rotation reduction that counts as "below"


def targets(summary: dict) -> dict:
    """The issue's targets on the gradient-level tracking set (textured = not in
    ``LOW_TEXTURE``): NF-KF no worse than NF; GS-Offline below NF and NF-KF in
    rotation MAE; zero false loops for GS-Offline on every episode."""
    out = {}
    tab = summary.get("tracking/gradients", {})
    if "nf" in tab and "nf-kf" in tab:
        rows = {}
        for o, nf in tab["nf"]["objects"].items():
            if o in LOW_TEXTURE or o not in tab["nf-kf"]["objects"]:
                continue
            kf = tab["nf-kf"]["objects"][o]
            rows[o] = {"rot_ratio": kf["rot_deg"] / nf["rot_deg"], "trans_ratio": kf["trans_mm"] / nf["trans_mm"],
                       "holds": kf["rot_deg"] <= nf["rot_deg"] and kf["trans_mm"] <= nf["trans_mm"]}
        out["nfkf_not_worse_than_nf"] = {"per_object": rows, "holds": all(r["holds"] for r in rows.values())}
    if "gelslam" in tab and ("nf" in tab or "nf-kf" in tab):
        rows = {}
        for o, gs in tab["gelslam"]["objects"].items():
            if o in LOW_TEXTURE:
                continue
            rows[o] = {f"rot_reduction_vs_{m}": 1.0 - gs["rot_deg"] / tab[m]["objects"][o]["rot_deg"]
                       for m in ("nf", "nf-kf") if m in tab and o in tab[m]["objects"]}
            # "below" beyond rounding: equal errors summed in another order do not count
            rows[o]["holds"] = all(v > BEATS_MARGIN for v in rows[o].values())
        mean = {f"rot_reduction_vs_{m}": 1.0 - tab["gelslam"]["mean_over_objects"]["rot_deg"]
                / tab[m]["mean_over_objects"]["rot_deg"] for m in ("nf", "nf-kf") if m in tab}
        out["gs_offline_beats_nf_rotation"] = {"per_object": rows, "mean_over_objects": mean, "paper_vs_nf": 0.46,
                                               "holds": all(r["holds"] for r in rows.values())}
    false = {t: v["gelslam"]["loops"] for t, v in summary.items() if "gelslam" in v}
    if false:
        out["gs_offline_zero_false_loops"] = {
            "per_table": false, "holds": all(v["episodes_with_false_loops"] == 0 for v in false.values())}
    return out


def table_iv(summary: dict) -> str:
    """Markdown tables in the paper's Table IV layout (mean over objects), one per
    episode set, plus the per-object rotation / translation means and loop counts."""
    lines = []
    for table, methods in summary.items():
        lines += [f"**{table}** (mean over objects: {', '.join(next(iter(methods.values()))['mean_objects'])})", "",
                  "| method | rx (deg) | ry (deg) | rz (deg) | x (mm) | y (mm) | z (mm) | estimated | loops (false) "
                  "| loop recall | ms/frame |", "|---|---|---|---|---|---|---|---|---|---|---|"]
        for row in methods.values():
            m = row["mean_over_objects"]
            loops = row.get("loops")
            lp = f"{loops['reported']} ({loops['false']})" if loops else "-"
            rc = f"{loops['recall']:.2f} of {loops['gt_loops']}" if loops else "-"
            total = row["timing_ms_median"].get("total", float("nan"))
            lines.append(f"| {row['label']} | " + " | ".join(f"{m[k]:.3f}" for k in (*ROT, *TRANS))
                         + f" | {row['estimated_fraction']:.2f} | {lp} | {rc} | {total:.0f} |")
        objects = sorted({o for row in methods.values() for o in row["objects"]})
        lines += ["", "| method | " + " | ".join(f"{o} rot / trans" for o in objects) + " |",
                  "|---|" + "---|" * len(objects)]
        for row in methods.values():
            cells = [f"{row['objects'][o]['rot_deg']:.3f} / {row['objects'][o]['trans_mm']:.3f}"
                     if o in row["objects"] else "-" for o in objects]
            lines.append(f"| {row['label']} | " + " | ".join(cells) + " |")
        if all("objects_shared_frames" in row for row in methods.values()):
            lines += ["", "On the frames every method estimates (each episode from the first of them):", "",
                      "| method | " + " | ".join(f"{o} rot / trans" for o in objects) + " |",
                      "|---|" + "---|" * len(objects)]
            for row in methods.values():
                sh = row["objects_shared_frames"]
                cells = [f"{sh[o]['rot_deg']:.3f} / {sh[o]['trans_mm']:.3f} ({sh[o]['n_frames']})"
                         if o in sh and sh[o]["n_frames"] else "- (0)" for o in objects]
                lines.append(f"| {row['label']} | " + " | ".join(cells) + " |")
        lines.append("")
    return "\n".join(lines)


def plot(path: Path, summary: dict) -> None:
    """Grouped bars of rotation and translation MAE (mean of the three axes) per object
    per method, one row per episode set; log scale."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    tables = list(summary)
    fig, axes = plt.subplots(len(tables), 2, figsize=(13, 3.6 * len(tables)), squeeze=False)
    for row, table in zip(axes, tables):
        methods = list(summary[table])
        objects = sorted({o for m in methods for o in summary[table][m]["objects"]})
        width = 0.8 / len(methods)
        for ax, key, unit in ((row[0], "rot_deg", "deg"), (row[1], "trans_mm", "mm")):
            for k, m in enumerate(methods):
                vals = [summary[table][m]["objects"].get(o, {}).get(key, np.nan) for o in objects]
                ax.bar(np.arange(len(objects)) + (k - (len(methods) - 1) / 2) * width, vals, width,
                       label=LABELS[m])
            ax.set_xticks(np.arange(len(objects)), objects)
            ax.set_yscale("log")
            ax.set_ylabel(f"{'rotation' if key == 'rot_deg' else 'translation'} MAE ({unit})")
            ax.set_title(f"{table}: mean of the 3 axes")
            ax.grid(axis="y", alpha=0.3, which="both")
        row[0].legend(fontsize=7, ncol=2)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


# ------------------------------------------------------------------ entry point


def previous_results(path: Path) -> dict | None:
    """The results of an earlier ``bench tracking`` JSON at ``path`` to merge into
    (``--append``), or ``None`` if there is no file. Raises :class:`BenchConfigError`
    for a file this benchmark did not write."""
    if not path.exists():
        return None
    try:
        doc = json.loads(path.read_text())
        res = doc["results"]
        ok = doc.get("benchmark") == "tracking" and all(k in res for k in ("runs", "summary", "episodes"))
    except (ValueError, KeyError, TypeError):
        ok = False
    if not ok:
        raise BenchConfigError(f"--append: {path} is not a tracking benchmark JSON of this version "
                               "(runs, summary, episodes); write to another --out")
    return res


def merge_results(old: dict | None, new: dict) -> dict:
    """``new`` results merged into ``old`` ones: summary tables and episodes of ``new``
    replacing those of the same key or name, ``runs`` keeping the earlier runs that still
    contribute a table, the targets recomputed on the merged summary. ``old`` ``None``:
    ``new`` as it is."""
    if old is None:
        return new
    names = {e["name"] for e in new["episodes"]}
    summary = {**old["summary"], **new["summary"]}
    runs = [r for r in old["runs"] if set(r["tables"]) - set(new["summary"])] + new["runs"]
    return {**new, "runs": runs, "summary": summary, "targets": targets(summary),
            "episodes": [e for e in old["episodes"] if e["name"] not in names] + new["episodes"]}


def run(args) -> Path:
    from tactile_slam.sim.episode import read_episode

    set_threads(args.threads)
    out_path = Path(args.out)
    old = previous_results(out_path) if args.append else None  # checked before any work
    config = load_config(args.config)  # checked before any work
    specs = episode_specs(args)
    cache = Path(args.cache)
    tmp = None if args.work else tempfile.TemporaryDirectory(prefix="bench_tracking_")
    work = Path(args.work or tmp.name)
    episodes, errors, shared = [], {}, {}
    t_start = time.perf_counter()
    try:
        for spec in specs:
            t0 = time.perf_counter()
            ep_dir = cached_episode(cache, spec, Config())
            ep = read_episode(ep_dir)
            entry = {"name": spec.name, "object": spec.label, "seed": spec.seed, "kind": spec.kind,
                     "object_file": None if spec.label == spec.object else str(Path(spec.object).resolve()),
                     "level": spec.level, "background": ep.background, "frames": spec.frames,
                     "table": spec.table,
                     "simulate_or_load_s": time.perf_counter() - t0, "methods": {}}
            for m in spec.methods:
                res, err = run_method(ep_dir, m, work / spec.name / m, config)
                entry["methods"][m] = res
                errors.setdefault((spec.table, m, spec.label), []).append(err)
                mae = res["per_axis_mae"]
                print(f"{spec.name:45s} {LABELS[m]:13s} rot {np.mean([mae[k] for k in ROT]):7.3f} deg  "
                      f"trans {np.mean([mae[k] for k in TRANS]):7.3f} mm  {res['wall_s']:6.1f} s", flush=True)
            ref, errs = shared_frame_errors({m: np.load(work / spec.name / m / "poses.npy") for m in spec.methods},
                                            ep.object_T_sensor, ep.in_contact)
            entry["shared_frames"] = {"reference_frame": ref, "frames": int(len(next(iter(errs.values()))))}
            for m, e in errs.items():
                shared.setdefault((spec.table, m, spec.label), []).append(e)
            episodes.append(entry)
    finally:
        if tmp is not None:
            tmp.cleanup()
    summary = summarise(episodes, errors, shared)
    run_info = {"settings": {k: v for k, v in vars(args).items() if k != "func"},
                "date": time.strftime("%Y-%m-%dT%H:%M:%S"), "machine": machine_info(),
                "tables": sorted(summary), "total_wall_s": time.perf_counter() - t_start}
    results = merge_results(old, {
        "runs": [run_info],
        "pooling": "per object: errors pooled over all scored frames of all seeds (NormalFlow's scripts); "
                   f"mean_over_objects: plain mean of the per-object values excluding {list(EXCLUDED_FROM_MEAN)}",
        "baseline_driver": "frame-to-frame like NF: frame i-1 -> i from the identity, composed; failure keeps "
                           "the previous pose",
        "loop_tolerance": {"trans_mm": 0.3, "rot_deg": 1.0},
        "summary": summary,
        "targets": targets(summary),
        "episodes": episodes,
    })
    out = write_json(out_path, "tracking", results)
    print(table_iv(summary))
    plot(Path(args.png) if args.png else out.with_suffix(".png"), results["summary"])
    return out
