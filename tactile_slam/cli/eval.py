"""``tactile-slam eval RUN_DIR --gt EPISODE_DIR``: score a run against a simulated episode.

The run's ``poses.npy`` (``(T, 4, 4)``, metres) holds each frame's sensor pose in the
sensor frame of the run's reference frame, the first frame with a pose (the first
contact frame of the main group), NaN where there is none. The episode's ``gt_poses.npy``
is ``object_T_sensor``; it is re-expressed as ``ref_T_curr`` for the same reference.
Metrics use the frames from the reference on that the ground truth has in contact.
Each reconstruction the run holds (``mesh.ply``: the watertight mesh, ``mesh_fused.ply``:
the fused keyframe surface, ``reconstructed_mesh.ply``: GelSLAM's name; all in metres in
the reference frame) is scored against ``object.ply`` too. Writes ``metrics.json`` and
``tracking_error.png``. When the run's ``stats.json`` names a ``source`` that is neither
the episode folder nor a file in it, the run was made on other data: eval warns
(:class:`SourceMismatchWarning`) and scores it all the same.
"""

from __future__ import annotations

import json
import math
import warnings
from pathlib import Path

import numpy as np

from tactile_slam.cli.arguments import output_folder, positive_int
from tactile_slam.eval.loop_metrics import loop_flags, loop_precision_recall
from tactile_slam.eval.tracking_metrics import AXES, per_axis_errors, tracking_report
from tactile_slam.eval.trajectory import TrajectoryError, read_poses, relative_to, valid_mask
from tactile_slam.sim.episode import read_episode, read_mesh

RECON_FILES = ("mesh.ply", "mesh_fused.ply", "reconstructed_mesh.ply")


class SourceMismatchWarning(UserWarning):
    """The run read something other than the episode it is scored against (its
    ``stats.json`` ``source`` is neither the episode folder nor a file in it): the scores
    compare it with another recording's ground truth."""


def register(sub) -> None:
    p = sub.add_parser("eval", help="score a run's poses (and reconstruction) against a simulated episode")
    p.add_argument("run_dir", help="run output folder with poses.npy")
    p.add_argument("--gt", required=True, help="episode folder written by `tactile-slam simulate`")
    p.add_argument("--out", default=None, type=output_folder, help="output folder (default: RUN_DIR)")
    p.add_argument("--no-recon", action="store_true", help="skip reconstruction metrics")
    p.add_argument("--touches", type=positive_int, default=100, help="NCD touches")
    p.add_argument("--samples", type=positive_int, default=100_000, help="surface samples per mesh (Chamfer, F-score)")
    p.set_defaults(func=run)


def evaluate_run(run_dir: str | Path, gt_dir: str | Path, recon: bool = True, touches: int = 100,
                 samples: int = 100_000) -> tuple[dict, dict]:
    """Metrics of a run against an episode.

    Returns:
        ``(metrics, series)``: the JSON-ready metrics and ``{"frames", "errors" (N, 6)}``
        per-axis errors over time for plotting.
    """
    run_dir = Path(run_dir)
    poses_path = run_dir / "poses.npy"
    if not poses_path.is_file():
        raise TrajectoryError(f"run folder {run_dir} has no poses.npy")
    est = read_poses(poses_path)
    ep = read_episode(gt_dir)
    source = run_source(run_dir)
    if source is not None and not reads_from(source, ep.path):
        warnings.warn(f"run {run_dir} read {source}, which is neither the episode {ep.path.resolve()} nor a file "
                      "in it: it is scored against another recording's ground truth", SourceMismatchWarning,
                      stacklevel=2)
    if len(est) != len(ep):
        raise TrajectoryError(f"run has {len(est)} frames but the episode has {len(ep)}")
    has = valid_mask(est)
    if not has.any():
        raise TrajectoryError(f"{poses_path} has no frame with a pose")
    ref = int(np.argmax(has))
    gt = relative_to(ep.object_T_sensor, ref)[ref:]
    est = est[ref:]
    frames = ep.in_contact[ref:]
    metrics = {
        "run": str(run_dir), "episode": str(Path(gt_dir)), "kind": ep.meta.get("kind"),
        "object": (ep.meta.get("object") or {}).get("name"), "reference_frame": ref,
        "gt_first_contact_frame": ep.first_contact,
        "tracking": tracking_report(est, gt, frames),
    }
    if (run_dir / "loops.json").is_file() and (run_dir / "keyframes.json").is_file():
        metrics["loops"] = loop_report(run_dir, ep.object_T_sensor)
    if (run_dir / "loops_held.json").is_file() and (run_dir / "keyframes.json").is_file():
        metrics["held_loops"] = held_loop_report(run_dir, ep.object_T_sensor)
    meshes = [name for name in RECON_FILES if (run_dir / name).is_file()] if recon else []
    if meshes:
        from tactile_slam.eval.recon_metrics import recon_report

        gt_mesh = ep.mesh()
        metrics["reconstruction"] = {
            name: recon_report(read_mesh(run_dir / name), gt_mesh, ep.object_T_sensor[ref], n_samples=samples,
                               n_touches=touches)
            for name in meshes}
    errors = per_axis_errors(est, gt)
    errors[~frames] = np.nan
    return metrics, {"frames": np.arange(ref, ref + len(est)), "errors": errors}


def run_source(run_dir: Path) -> str | None:
    """The ``source`` the run's ``stats.json`` names (an absolute path, or a camera's
    name); ``None`` for a run without ``stats.json`` or one written before it had the key."""
    path = run_dir / "stats.json"
    if not path.is_file():
        return None
    try:
        stats = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise TrajectoryError(f"cannot read {path}: {exc}") from exc
    if not isinstance(stats, dict):
        raise TrajectoryError(f"{path} is not a JSON object")
    source = stats.get("source")
    if source is not None and not isinstance(source, str):
        raise TrajectoryError(f"{path}: source must be a path, got {source!r}")
    return source


def reads_from(source: str, episode_dir: Path) -> bool:
    """Whether ``source`` is the episode folder or a file inside it (symlinks resolved). A
    source that is not an absolute path (a camera, a looped replay) never is."""
    if not Path(source).is_absolute():
        return False
    src, ep = Path(source).resolve(), Path(episode_dir).resolve()
    return src == ep or ep in src.parents


def _read_loops(path: Path, held: bool = False) -> list[dict]:
    """The loop records of ``loops.json`` (or, ``held``, ``loops_held.json``, each with a
    ``reason``); :class:`TrajectoryError` naming the file when they are malformed."""
    try:
        loops = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise TrajectoryError(f"cannot read {path}: {exc}") from exc
    keys = {"ref_id", "tar_id", "ref_T_tar"} | ({"reason"} if held else set())
    if not isinstance(loops, list) or not all(isinstance(lp, dict) and keys <= lp.keys() for lp in loops):
        raise TrajectoryError(f"{path} is not a list of loop records with {sorted(keys)}")
    for lp in loops:
        sigma = lp.get("tilt_sigma_deg")
        if sigma is not None and not (isinstance(sigma, (int, float)) and math.isfinite(sigma) and sigma > 0):
            raise TrajectoryError(f"{path}: tilt_sigma_deg must be a positive number or null, got {sigma!r}")
    return loops


def _precision(loops: list[dict], video: dict[int, int], object_T_sensor: np.ndarray, source: Path) -> dict:
    """:func:`loop_precision_recall` of loop records whose keyframe ids map to video frames
    through ``video``."""
    unknown = sorted({i for lp in loops for i in (lp["ref_id"], lp["tar_id"])} - video.keys())
    if unknown:
        raise TrajectoryError(f"{source}: loops through keyframes {unknown[:5]} that keyframes.json does not list")
    pairs = np.array([[video[lp["ref_id"]], video[lp["tar_id"]]] for lp in loops], dtype=np.int64).reshape(-1, 2)
    rel = np.array([lp["ref_T_tar"] for lp in loops], dtype=np.float64).reshape(-1, 4, 4)
    known, sigma = loop_flags(loops)
    return loop_precision_recall(pairs, rel, object_T_sensor, depth_known=known, tilt_sigma_deg=sigma)


def _video_of(run_dir: Path) -> dict[int, int]:
    """Keyframe id -> video index, from the run's ``keyframes.json``."""
    return {k["id"]: k["video_index"] for k in json.loads((run_dir / "keyframes.json").read_text())}


def loop_report(run_dir: Path, object_T_sensor: np.ndarray) -> dict:
    """Precision of the run's accepted loops (``loops.json``) against ground truth: each
    loop's keyframes map to video frames through ``keyframes.json``."""
    path = run_dir / "loops.json"
    return _precision(_read_loops(path), _video_of(run_dir), object_T_sensor, path)


def held_loop_report(run_dir: Path, object_T_sensor: np.ndarray) -> dict[str, dict]:
    """:func:`loop_report` of the verified loops the back end held out of the graph
    (``loops_held.json``), per reason (``waiting``, ``repetitive``, ...): whether the loops
    it waited on or dropped were right."""
    path = run_dir / "loops_held.json"
    held, video = _read_loops(path, held=True), _video_of(run_dir)
    return {r: _precision([lp for lp in held if lp["reason"] == r], video, object_T_sensor, path)
            for r in sorted({lp["reason"] for lp in held})}


def plot_errors(path: Path, frames: np.ndarray, errors: np.ndarray, fps: float, title: str) -> None:
    """Per-axis absolute error over time: translations (mm) and rotations (deg)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t = frames / fps
    fig, axes = plt.subplots(2, 1, figsize=(9, 5), sharex=True)
    for i, name in enumerate(AXES):
        ax = axes[0] if i < 3 else axes[1]
        ax.plot(t, errors[:, i], lw=0.8, label=name.split("_")[0])
    axes[0].set_ylabel("|error| (mm)")
    axes[1].set_ylabel("|error| (deg)")
    axes[1].set_xlabel("time (s)")
    for ax in axes:
        ax.legend(loc="upper left", fontsize=8)
        ax.grid(alpha=0.3)
    axes[0].set_title(title)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def run(args) -> int:
    metrics, series = evaluate_run(args.run_dir, args.gt, recon=not args.no_recon, touches=args.touches,
                                   samples=args.samples)
    out = Path(args.out) if args.out else Path(args.run_dir)
    out.mkdir(parents=True, exist_ok=True)
    (out / "metrics.json").write_text(json.dumps(metrics, indent=2))
    ep = read_episode(args.gt)
    fps = float((ep.meta.get("sensor") or {}).get("fps", 25.0))
    plot_errors(out / "tracking_error.png", series["frames"], series["errors"], fps,
                f"{metrics['object']} {metrics['kind']}: per-axis tracking error")
    mae = metrics["tracking"]["per_axis_mae"]
    print("per-axis MAE: " + ", ".join(f"{k} {mae[k]:.3f}" for k in AXES) + f" over {mae['n_frames']} frames")
    if "loops" in metrics:
        lm = metrics["loops"]
        full = "" if lm["correct_full_pose"] == lm["correct"] else (
            f" ({lm['correct_full_pose']} within 1 deg in full pose; loops from video are scored out of plane"
            " within their tilt_sigma_deg)")
        print(f"loops: {lm['correct']} of {lm['reported']} correct{full}")
    if metrics.get("held_loops"):
        print("verified loops held out of the graph (correct of held): "
              + ", ".join(f"{r} {m['correct']} of {m['reported']}" for r, m in metrics["held_loops"].items()))
    print(f"wrote {out / 'metrics.json'} and {out / 'tracking_error.png'}")
    return 0
