"""Reconstruction accuracy (CD, F-score, NCD) and fusion/meshing time on simulated scans.

For each object and size (the paper's Table VI objects at its small and large print
sizes) a hand-held scan is simulated with :mod:`tactile_slam.sim` (``--level``
gradients: noise-free gradient maps; image: GelSight Mini video through the colour
model, decoded by the shipped calibration model), the full system
(:class:`tactile_slam.pipeline.offline.OfflinePipeline`, method ``gelslam``) runs on it,
and :func:`tactile_slam.recon.reconstruct` meshes the run's keyframes four ways:

* ``gt_all``: every keyframe of the run, ground-truth poses (the mapping's own limit);
* ``estimated``: the largest connected group, the poses the system estimated;
* ``gt_group``: the same group's keyframes with ground-truth poses, so the gap between
  ``gt_all`` and ``gt_group`` is what unconnected sessions cost and the gap between
  ``gt_group`` and ``estimated`` is what pose error costs;
* ``gt_joinable``: the largest group an ideal loop closure could form from the run's
  keyframes (sessions joined wherever two of their keyframes truly share at least 5 mm^2
  of surface, :func:`tactile_slam.eval.loop_metrics.joinable_groups`), ground-truth
  poses: the best any system can do on the scan, since sessions that share no surface
  with the rest cannot be placed by touch.

Each run's ``system`` entry also holds the groups the system formed, those an ideal loop
closure could form, and the ``revisit_funnel``
(:func:`tactile_slam.eval.loop_funnel.revisit_funnel`): how many of the pairs that
truly share surface across sessions reach each stage of loop detection, and the
``loop_precision`` of the run's accepted loops against ground truth
(:func:`tactile_slam.cli.eval.loop_report`: a loop is correct within 1 deg and 0.3 mm, one
from video out of plane within its declared ``tilt_sigma_deg``; ``correct_full_pose`` by 1 deg alone),
and ``held_loops``: the same per reason for the verified loops the back end kept out of
the graph (:func:`tactile_slam.cli.eval.held_loop_report`).

Each Poisson mesh is scored with :func:`tactile_slam.eval.recon_metrics.recon_report`
at the ground-truth placement of its start frame and after ICP; the fused grid mesh
(which never closes untouched regions) gets the surface metrics at that placement.
``--timing N`` also times fusion and meshing of N touches spread over a 120 mm lime
(every touch a coverage keyframe); ``--objects`` with no names skips the table.
"""

from __future__ import annotations

import json
import tempfile
import time
from collections import Counter
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import torch

from tactile_slam.bench.common import rendered_frames, write_json
from tactile_slam.cli.arguments import positive_int
from tactile_slam.config import Config, load_config
from tactile_slam.cli.eval import held_loop_report, loop_report
from tactile_slam.eval.loop_funnel import revisit_funnel
from tactile_slam.eval.loop_metrics import joinable_groups
from tactile_slam.eval.recon_metrics import recon_report, surface_metrics, touch_poses
from tactile_slam.geometry.frame import FrameBuilder, crop_to_contact
from tactile_slam.io import open_source
from tactile_slam.pipeline.offline import OfflinePipeline, RunOptions
from tactile_slam.recon import ReconError, reconstruct
from tactile_slam.sim.episode import SimulationSettings, read_episode, simulate_episode
from tactile_slam.sim.objects import make_object
from tactile_slam.sim.renderer import GelRenderer
from tactile_slam.tracking.keyframe import Keyframe

# The paper's Table VI sizes (mm) of the small and large prints.
SIZES_MM = {"seed": (9.5, 14.3), "shell": (18.4, 27.6), "dice": (10.0, 15.0), "lime": (15.0, 29.9)}
VARIANTS = ("gt_all", "estimated", "gt_group", "gt_joinable")
JOIN_OVERLAP_MM2 = 5.0  # shared surface that lets an ideal loop closure join two sessions


def add_arguments(parser) -> None:
    parser.add_argument("--objects", nargs="*", default=list(SIZES_MM), choices=sorted(SIZES_MM),
                        help="objects of the accuracy table (none: skip it)")
    parser.add_argument("--sizes", nargs="+", default=["small", "large"], choices=["small", "large"])
    parser.add_argument("--frames", type=positive_int, default=None,
                        help="simulated scan frames per object (default: 1500 small, 3000 large)")
    parser.add_argument("--level", choices=["gradients", "image"], default="gradients",
                        help="simulated input: gradient maps, or video through the calibration model")
    parser.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=VARIANTS)
    parser.add_argument("--samples", type=positive_int, default=50_000, help="surface samples for CD/F-score")
    parser.add_argument("--touches", type=positive_int, default=50, help="NCD touches")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--partial", action="store_true", help="trim the Poisson mesh (watertight=False)")
    parser.add_argument("--work", default=None, help="keep episodes and runs here (default: a temporary folder)")
    parser.add_argument("--config", default=None,
                        help="YAML config or preset for the system runs (default: GelSight Mini defaults)")
    parser.add_argument("--timing", type=int, default=0, metavar="N",
                        help="also time fusion + meshing of N touches spread over a 120 mm lime")


def system_run(episode_dir: Path, run_dir: Path, config: Config) -> tuple[list, dict, dict, dict]:
    """Run the full system on a simulated episode.

    Returns:
        keyframes, ``{id: (4, 4) start_T_kf}`` float64 estimated poses, ``{id: group}``,
        and the run's statistics.
    """
    source = open_source(episode_dir)
    result = OfflinePipeline(source, config, run_dir, RunOptions(progress=False, mesh=False)).run()
    records = json.loads((run_dir / "keyframes.json").read_text())
    poses = {r["id"]: torch.tensor(r["pose"], dtype=torch.float64) for r in records}
    groups = {r["id"]: r["group"] for r in records}
    return result.keyframes, poses, groups, result.stats


def joinable_labels(keyframes: list, gt: np.ndarray, config: Config) -> dict:
    """``{id: label}`` of the groups an ideal loop closure could form from ``keyframes``
    (:func:`~tactile_slam.eval.loop_metrics.joinable_groups` on their true poses and
    maps). ``gt``: ``(T, 4, 4)`` object_T_sensor."""
    frames = [k.frame for k in keyframes]  # expanded once per keyframe
    height = np.stack([f.height[0].numpy() for f in frames])
    contact = np.stack([f.contact[0].numpy() for f in frames])
    label = joinable_groups(np.array([k.session for k in keyframes]), gt[[k.video_index for k in keyframes]],
                            height, contact, config.sensor.mm_per_px, JOIN_OVERLAP_MM2)
    return {k.id: int(g) for k, g in zip(keyframes, label)}


def variant_input(variant: str, keyframes: list, est: dict, groups: dict, gt: np.ndarray,
                  joinable: dict | None = None):
    """Keyframes, ``(K, 4, 4)`` start_T_kf and ``(4, 4)`` ground-truth object_T_start
    of one variant (see the module docstring). ``groups``: ``{id: group}`` of the run;
    ``joinable``: ``{id: label}`` (:func:`joinable_labels`), needed by ``gt_joinable``;
    ``gt``: ``(T, 4, 4)`` object_T_sensor."""
    if variant == "gt_all":
        kfs = keyframes
    else:
        labels = joinable if variant == "gt_joinable" else groups
        if labels is None:
            raise ValueError("the gt_joinable variant needs the joinable groups")
        label = Counter(labels[k.id] for k in keyframes).most_common(1)[0][0]
        kfs = [k for k in keyframes if labels[k.id] == label]
    o_T_kf = np.stack([gt[k.video_index] for k in kfs])
    if variant == "estimated":
        poses = torch.stack([est[k.id] for k in kfs])
        return kfs, poses, o_T_kf[0] @ np.linalg.inv(poses[0].numpy())
    return kfs, torch.from_numpy(np.linalg.inv(o_T_kf[0]) @ o_T_kf), o_T_kf[0]


def timing_run(n_touches: int, seed: int, config: Config) -> dict:
    """Fusion + meshing time for ``n_touches`` shallow presses (0.3 mm) at farthest-point
    locations of a 120 mm lime: large enough that most touches stay coverage keyframes."""
    gt = make_object("lime", 120.0, seed)
    renderer = GelRenderer(gt, config)
    o_T_s = touch_poses(gt, n_touches, depth_mm=0.3, seed=seed, config=config, renderer=renderer)
    kfs, poses = [], []
    for pose, frame in zip(o_T_s, rendered_frames(renderer, FrameBuilder(config), o_T_s)):
        if bool(frame.contact.any()):
            # stored as the pipeline stores keyframes by the time it meshes: around the contact
            kfs.append(Keyframe(id=len(kfs), session=0, maps=crop_to_contact(frame), new_session=not kfs,
                                prev_T_kf=torch.eye(4, dtype=torch.float64)))
            poses.append(pose)
    o_T_s = np.stack(poses)
    t0 = time.perf_counter()
    res = reconstruct(kfs, torch.from_numpy(np.linalg.inv(o_T_s[0]) @ o_T_s), config)
    total = time.perf_counter() - t0
    out = {"touches": n_touches, "keyframes": len(kfs), "total_s": total, "stats": res.stats}
    print(f"timing: {len(kfs)} keyframes, {res.stats['coverage_keyframes']} coverage keyframes: coverage "
          f"{res.stats['coverage_s']:.1f} s, fusion {res.stats['fusion_s']:.1f} s, meshing "
          f"{res.stats['meshing_s']:.1f} s, total {total:.1f} s", flush=True)
    return out


def object_run(name: str, size_label: str, args, config: Config, work: Path) -> Iterator[dict]:
    """Simulate, run the system and score every variant of one object and size (one entry
    per variant, as each is scored)."""
    size = SIZES_MM[name][0 if size_label == "small" else 1]
    ep, run_dir = work / f"{name}_{size_label}" / "episode", work / f"{name}_{size_label}" / "run"
    t0 = time.perf_counter()
    frames = args.frames or (1500 if size_label == "small" else 3000)
    simulate_episode(ep, SimulationSettings(object=name, kind="scan", seed=args.seed, frames=frames,
                                            level=args.level, size_mm=size))
    t1 = time.perf_counter()
    keyframes, est, groups, run_stats = system_run(ep, run_dir, config)
    t2 = time.perf_counter()
    episode = read_episode(ep)
    gt_mesh = episode.mesh()
    system = {k: run_stats.get(k) for k in ("frames", "contact_frames", "keyframes", "sessions", "groups", "loops",
                                            "coverage_keyframes", "fps")}
    joinable = joinable_labels(keyframes, episode.object_T_sensor, config)
    funnel = revisit_funnel(keyframes, episode.object_T_sensor[[k.video_index for k in keyframes]], config,
                            JOIN_OVERLAP_MM2)
    system |= {"largest_group": Counter(groups.values()).most_common(1)[0][1],
               "joinable_groups": len(set(joinable.values())),
               "joinable_largest": Counter(joinable.values()).most_common(1)[0][1],
               "revisit_funnel": funnel,
               "loop_precision": loop_report(run_dir, episode.object_T_sensor),
               "held_loops": held_loop_report(run_dir, episode.object_T_sensor)}
    print(f"{name:6s} {size_label:5s} {system['sessions']} sessions -> {system['groups']} groups, largest "
          f"{system['largest_group']} of {len(keyframes)} keyframes; an ideal loop closure: "
          f"{system['joinable_groups']} groups, largest {system['joinable_largest']}; revisits between sessions "
          + " -> ".join(f"{k} {v}" for k, v in funnel.items())
          + f"; loops {system['loop_precision']['correct']} of {system['loop_precision']['reported']} correct"
          + "".join(f", held {r} {m['correct']} of {m['reported']}" for r, m in system["held_loops"].items()),
          flush=True)
    for variant in args.variants:
        kfs, poses, object_T_start = variant_input(variant, keyframes, est, groups, episode.object_T_sensor, joinable)
        entry = {"object": name, "size": size_label, "size_mm": size, "frames": frames, "level": args.level,
                 "background": episode.background, "variant": variant,
                 "keyframes": len(kfs), "simulation_s": t1 - t0, "system_s": t2 - t1, "system": system}
        try:
            res = reconstruct(kfs, poses, config)
        except ReconError as exc:  # e.g. a group of touches too small to fuse: recorded, the others go on
            entry["skipped"] = str(exc)
            print(f"{name:6s} {size_label:5s} {variant:9s} K {len(kfs):4d} skipped: {exc}", flush=True)
            yield entry
            continue
        entry["stats"] = res.stats
        entry["mesh"] = recon_report(res.mesh.to_open3d(), gt_mesh, object_T_start, icp=True,
                                     n_samples=args.samples, n_touches=args.touches, seed=args.seed, config=config)
        fused = res.fused_mesh.to_open3d().transform(object_T_start)
        fused.compute_triangle_normals()
        entry["fused"] = {"gt_pose": surface_metrics(fused, gt_mesh, args.samples, args.seed)}
        print(_line(entry), flush=True)
        yield entry


def run(args):
    torch.set_num_threads(1)
    config = load_config(args.config)
    config.recon.watertight = not args.partial
    doc = {"settings": vars(args) | {"func": None}, "runs": []}
    path = write_json(args.out, "reconstruction", doc)
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(args.work) if args.work else Path(tmp)
        for name in args.objects:
            for size_label in args.sizes:
                for entry in object_run(name, size_label, args, config, work):
                    doc["runs"].append(entry)
                    # rewritten after every variant so a long benchmark leaves partial results
                    path = write_json(args.out, "reconstruction", doc)
    if args.timing:
        doc["timing"] = timing_run(args.timing, args.seed, config)
        path = write_json(args.out, "reconstruction", doc)
    return path


def _line(e: dict) -> str:
    m, st = e["mesh"], e["stats"]
    return (f"{e['object']:6s} {e['size']:5s} {e['variant']:9s} K {e['keyframes']:4d} "
            f"cov {st['coverage_keyframes']:4d}  fused CD {e['fused']['gt_pose']['chamfer_mm']:.3f} "
            f"(acc {e['fused']['gt_pose']['recon_to_gt_mm']:.3f})  mesh "
            f"CD {m['gt_pose']['chamfer_mm']:.3f} / ICP {m['icp']['chamfer_mm']:.3f} mm "
            f"(acc {m['icp']['recon_to_gt_mm']:.3f}, compl {m['icp']['gt_to_recon_mm']:.3f})  "
            f"F@0.1 {m['icp']['fscore']['0.1']['f']:.3f}  NCD {m['gt_pose']['ncd']:.3f} / {m['icp']['ncd']:.3f}  "
            f"fusion {st['coverage_s'] + st['fusion_s']:.1f} s meshing {st['meshing_s']:.1f} s")
