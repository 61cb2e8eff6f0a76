"""Loop detection: recall/precision on simulated revisits, per-keyframe time vs map size, SIFT backends.

Keyframes are every ``--stride``-th in-contact frame of simulated episodes, rendered by
:class:`tactile_slam.sim.renderer.GelRenderer` with ground-truth sensor poses, and
queried in order. A contact period is a session.

* **Accuracy**: an accepted loop is correct when its ``ref_T_tar`` is within 0.3 mm and
  1 degree of the truth. A pair is a *true revisit* when, at the true relative pose,
  at least ``--overlap`` of the reference's contact pixels land in the query's contact.
  Pair recall = correct loops / true revisits among the candidates offered; query
  recall = queries with a correct loop / queries with a true revisit; precision =
  correct / accepted. Run twice: ``coverage+gate`` (the pipeline's situation: the
  candidates are the active coverage keyframes, one group per session, true poses as
  the pose estimate) and ``all+no_gate`` (every earlier keyframe is a candidate, every
  keyframe its own group: nothing but the data decides; the false-loop stress test).
* **Timing**: median wall time of adding a keyframe and detecting its loops over the
  last queries of maps of ``--sizes`` keyframes of a long scan, every earlier keyframe a
  candidate (the worst case: no coverage pruning), and of the descriptor-index query alone
  up to the largest ``--index-sizes`` (keyframe descriptors replicated with noise).
* **Backends**: OpenCV vs kornia SIFT: extraction time and accuracy on one episode.
* **Back end** (``--backend-objects``): the tracker runs over every simulated frame of an
  episode, and its keyframes (with their real odometry) go through the
  :class:`~tactile_slam.backend.BackEnd` twice: with the loop gate (``loop.consistency``:
  loops checked against the map, merges only on agreeing loops) and without it (every
  verified loop accepted, groups merged on one loop). Scored on the loops that end up in
  the graph: accepted, false, query recall (queries with a correct loop / queries with a
  true revisit among all earlier keyframes), groups left, and the gate's counters.
"""

from __future__ import annotations

import argparse
import math
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from tactile_slam.bench.common import rendered_frames, set_threads, timing_stats, write_json
from tactile_slam.cli.arguments import positive_int
from tactile_slam.config import Config, load_config
from tactile_slam.geometry.frame import FrameBuilder, crop_to_contact
from tactile_slam.loop.coverage import CoverageSet
from tactile_slam.loop.detector import LoopDetector
from tactile_slam.loop.retrieval import DescriptorIndex, IndexSettings
from tactile_slam.posegraph import se3
from tactile_slam.registration.normalflow import prepare_reference
from tactile_slam.registration.result import pose_error
from tactile_slam.tracking.keyframe import Keyframe

EYE = torch.eye(4, dtype=torch.float64)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--objects", nargs="*", default=["seed", "shell", "dice", "lime", "knurled"])
    p.add_argument("--kinds", nargs="+", default=["tracking", "scan"], help="episode kinds for accuracy")
    p.add_argument("--frames", type=positive_int, default=520, help="frames per tracking episode (scans: 3x)")
    p.add_argument("--stride", type=positive_int, default=8, help="keyframe every N in-contact frames (paper: 7.7)")
    p.add_argument("--overlap", type=float, default=0.3, help="true-revisit overlap fraction")
    p.add_argument("--modes", nargs="+", default=["full", "only_sift"], help="loop modes to score")
    p.add_argument("--sizes", nargs="*", type=positive_int, default=[100, 1000],
                   help="map sizes for detect timing (none: skip)")
    p.add_argument("--index-sizes", nargs="*", type=positive_int, default=[100, 1000, 5000])
    p.add_argument("--timing-object", default="shell")
    p.add_argument("--queries", type=positive_int, default=30, help="timed queries per map size")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--backend-objects", nargs="*", default=["seed", "shell", "lime", "knurled"],
                   help="objects for the back-end (loop gate) accuracy; none: skip")
    p.add_argument("--backend-kinds", nargs="+", default=["scan"])
    p.add_argument("--threads", type=positive_int, default=None,
                   help="torch CPU threads (default: torch's choice; the online back end runs loop detection on 1)")
    p.add_argument("--config", default=None,
                   help="YAML config or preset for the tracker, detector and back end (default: GelSight Mini)")


# ------------------------------------------------------------------ simulated keyframes


def simulate_keyframes(obj: str, kind: str, n_frames: int, stride: int, seed: int, config: Config,
                       max_keyframes: int | None = None) -> tuple[list[Keyframe], np.ndarray]:
    """Keyframes of one simulated episode and their true ``object_T_sensor`` ``(K, 4, 4)``."""
    from tactile_slam.sim.motions import make_motion
    from tactile_slam.sim.objects import make_object
    from tactile_slam.sim.renderer import GelRenderer

    renderer = GelRenderer(make_object(obj, seed=seed), config)
    motion = make_motion(renderer, kind, n_frames, seed=seed)
    pressed = np.flatnonzero(motion.pressed)
    session = np.cumsum(np.r_[1, np.diff(pressed) > 1]) - 1  # contact periods
    pick = np.flatnonzero(np.arange(len(pressed)) % stride == 0)
    if max_keyframes is not None:
        pick = pick[:max_keyframes]
    idx = pressed[pick]
    kfs, poses = [], []
    for j, frame in enumerate(rendered_frames(renderer, FrameBuilder(config), motion.object_T_sensor[idx], idx)):
        if not bool(frame.in_contact[0]):
            continue
        sess = int(session[pick[j]])
        # stored as the trackers store keyframes: the maps around the contact
        kfs.append(Keyframe(len(kfs), sess, crop_to_contact(frame), not kfs or kfs[-1].session != sess, EYE.clone()))
        poses.append(motion.object_T_sensor[idx[j]])
    return kfs, np.asarray(poses)


def tracked_keyframes(obj: str, kind: str, n_frames: int, seed: int, config: Config) -> tuple[list[Keyframe],
                                                                                                np.ndarray]:
    """The tracker's keyframes over every frame of a simulated episode (gradient level), and
    the true ``object_T_sensor`` of every frame ``(T, 4, 4)`` (index = ``video_index``)."""
    from tactile_slam.sim.motions import make_motion
    from tactile_slam.sim.objects import make_object
    from tactile_slam.sim.renderer import GelRenderer
    from tactile_slam.tracking.tracker import NormalFlowRegistrar, Tracker

    renderer = GelRenderer(make_object(obj, seed=seed), config)
    motion = make_motion(renderer, kind, n_frames, seed=seed)
    tracker = Tracker(config.tracking, NormalFlowRegistrar(config.normalflow, config.tracking))
    kfs: list[Keyframe] = []
    for frame in rendered_frames(renderer, FrameBuilder(config), motion.object_T_sensor):
        kfs += tracker.step(frame).keyframes
    kfs += tracker.finish()
    for kf in kfs:  # held for the whole scan: no preparations pinned (replays prepare their queries)
        kf.prepared = None
    return kfs, np.asarray(motion.object_T_sensor)


def true_revisits(kfs: list[Keyframe], obj_T: torch.Tensor, overlap: float, reach_m: float) -> set[tuple[int, int]]:
    """Pairs ``(r, t)``, ``r < t`` (not ``t - 1`` of the same session), where at the true
    relative pose at least ``overlap`` of ``r``'s contact lands in ``t``'s; only pairs whose
    sensor origins are within ``reach_m`` are tested."""
    pos = obj_T[:, :3, 3]
    out = set()
    for t in range(len(kfs)):
        near = torch.nonzero(torch.linalg.vector_norm(pos[:t] - pos[t], dim=1) <= reach_m).flatten().tolist()
        for r in near:
            if r == t - 1 and kfs[r].session == kfs[t].session:
                continue
            if overlap_fraction(kfs[r], kfs[t], se3.inverse(obj_T[t]) @ obj_T[r]) >= overlap:
                out.add((r, t))
    return out


def loop_error(lp, true_ref_T_tar: torch.Tensor, kmap: dict[int, Keyframe]) -> tuple[float, float]:
    """Rotation (deg) and translation (mm) error of a loop against the true ``ref_T_tar``
    (:func:`~tactile_slam.registration.result.pose_error`); when either keyframe had no
    undeformed gel in view (:attr:`Keyframe.depth_known`) the translation error leaves out
    z, which the loop cannot measure: it carries that keyframe's guessed height zero, as
    the keyframe's odometry does."""
    rot, trans = pose_error(lp.ref_T_tar[None], true_ref_T_tar[None])
    if not (kmap[lp.ref_id].depth_known and kmap[lp.tar_id].depth_known):
        trans = torch.linalg.vector_norm(lp.ref_T_tar[:2, 3].double() - true_ref_T_tar[:2, 3].double()) * 1000.0
    return float(rot), float(trans)


def wrong_loop(lp, obj_T: torch.Tensor, kmap: dict[int, Keyframe]) -> dict | None:
    """``None`` when the loop is correct (within 1 deg and 0.3 mm of the truth, method.md's
    release gate), else a record of it for the JSON.

    Args:
        obj_T: ``(K, 4, 4)`` object-from-sensor pose of each keyframe id, ground truth.
    """
    rot, trans = loop_error(lp, se3.inverse(obj_T[lp.ref_id]) @ obj_T[lp.tar_id], kmap)
    if rot <= 1.0 and trans <= 0.3:
        return None
    return {"ref": lp.ref_id, "tar": lp.tar_id, "rot_deg": rot, "trans_mm": trans,
            "ccs": lp.ccs, "scr": lp.scr, "inliers": lp.inliers}


def score_backend(kfs: list[Keyframe], obj_T_frames: np.ndarray, config: Config,
                  revisits: set[tuple[int, int]]) -> dict:
    """Run the back end over tracked keyframes; score the loops in its final graph."""
    from tactile_slam.backend import BackEnd

    obj_T = torch.as_tensor(obj_T_frames, dtype=torch.float64)[[k.video_index for k in kfs]]
    be = BackEnd(config)
    times = []
    for k in kfs:
        t0 = time.perf_counter()
        be.add(k)
        times.append(time.perf_counter() - t0)
    be.finish()
    correct, wrong, hit = 0, [], set()
    kmap = {k.id: k for k in kfs}
    for lp in be.loops:
        record = wrong_loop(lp, obj_T, kmap)
        if record is None:
            correct += 1
            hit.add(lp.tar_id)
        else:
            wrong.append(record)
    queries = {t for _, t in revisits}
    sizes = sorted((be.sessions.size(g) for g in be.sessions.groups), reverse=True)
    return {"keyframes": len(kfs), "sessions": len({k.session for k in kfs}), "true_revisits": len(revisits),
            "verified": be.detector.stats.loops, "accepted": len(be.loops), "correct": correct, "false": len(wrong),
            "query_recall": len(hit & queries) / len(queries) if queries else None,
            "groups": len(sizes), "largest_group": sizes[0] if sizes else 0, "summary": be.summary(),
            "add_time": timing_stats(times), "false_loops": wrong[:20]}


def overlap_fraction(ref: Keyframe, tar: Keyframe, tar_T_ref: torch.Tensor) -> float:
    """Fraction of ``ref``'s contact pixels that land in ``tar``'s contact at ``tar_T_ref``."""
    f = ref.frame
    h, w = f.shape
    s = f.mm_per_px / 1000.0
    r, c = torch.nonzero(f.contact[0], as_tuple=True)
    if r.numel() == 0:
        return 0.0
    pts = torch.stack([(c - (w - 1) / 2) * s, (r - (h - 1) / 2) * s, f.height[0, r, c].double() * s], 1).double()
    moved = pts @ tar_T_ref[:3, :3].T + tar_T_ref[:3, 3]
    if float(tar_T_ref[2, 2]) <= 0:
        return 0.0
    cc = torch.round(moved[:, 0] / s + (w - 1) / 2).long()
    rr = torch.round(moved[:, 1] / s + (h - 1) / 2).long()
    inside = (cc >= 0) & (cc < w) & (rr >= 0) & (rr < h)
    hit = torch.zeros_like(inside)
    hit[inside] = tar.frame.contact[0][rr[inside], cc[inside]]
    return float(hit.double().mean())


def score_episode(kfs: list[Keyframe], obj_T: np.ndarray, config: Config, mode: str, realistic: bool,
                  overlap: float) -> dict:
    """Run detection over an episode and score it against the truth.

    ``realistic``: candidates are the active coverage keyframes (coverage set on the true
    poses, one group per session) and the pose gate uses the true poses; otherwise every
    earlier keyframe is a candidate and nothing is gated (every keyframe its own group).
    """
    det = LoopDetector(config, mode=mode)
    cov = CoverageSet(config) if realistic else None
    kmap = {k.id: k for k in kfs}
    obj_T = torch.as_tensor(obj_T, dtype=torch.float64)
    heads, start_T, group = {}, {}, {}
    true_pairs, correct, wrong, times = set(), 0, [], []
    queries_true, queries_hit = set(), set()
    for k in kfs:
        det.add(k)
        head = heads.setdefault(k.session, k.id)
        start_T[k.id] = se3.inverse(obj_T[head]) @ obj_T[k.id]
        group[k.id] = k.session if realistic else k.id
        eligible = cov.active if cov is not None else [r for r in kmap if r < k.id]
        for r in eligible:
            if r == k.id - 1 and kmap[r].session == k.session:
                continue
            if overlap_fraction(kmap[r], k, se3.inverse(obj_T[k.id]) @ obj_T[r]) >= overlap:
                true_pairs.add((r, k.id))
                queries_true.add(k.id)
        t0 = time.perf_counter()
        loops = det.detect(k, eligible, group, start_T, kmap)
        times.append(time.perf_counter() - t0)
        if cov is not None:
            before = set(cov.active)
            cov.add(k, start_T[k.id], group[k.id])
            for r in before | {k.id}:
                if not cov.is_active(r):
                    det.remove(r)
        for lp in loops:
            record = wrong_loop(lp, obj_T, kmap)
            if record is None:
                correct += 1
                queries_hit.add(k.id)
            else:
                wrong.append(record)
    accepted = correct + len(wrong)
    return {
        "keyframes": len(kfs), "sessions": len({k.session for k in kfs}),
        "keyframes_depth_unknown": sum(not k.depth_known for k in kfs),
        "coverage_keyframes": len(cov.active) if cov is not None else None, "true_revisits": len(true_pairs),
        "accepted": accepted, "correct": correct, "false": len(wrong),
        "precision": correct / accepted if accepted else None,
        "pair_recall": correct / len(true_pairs) if true_pairs else None,
        "query_recall": len(queries_hit & queries_true) / len(queries_true) if queries_true else None,
        "detect_time": timing_stats(times), "stats": det.stats.to_dict(), "false_loops": wrong[:20],
    }


def timing_vs_size(kfs: list[Keyframe], obj_T: np.ndarray, config: Config, sizes: list[int], queries: int) -> dict:
    """Median detect time over the last ``queries`` keyframes of maps of each size: the
    candidates cropped to their contact, the query with its full maps, as in the pipeline."""
    out = {}
    obj_T = torch.as_tensor(obj_T, dtype=torch.float64)
    for n in sizes:
        if n > len(kfs):
            continue
        det = LoopDetector(config)
        kmap = {k.id: k for k in kfs[:n]}
        start_T = {k.id: se3.inverse(obj_T[0]) @ obj_T[k.id] for k in kfs[:n]}
        group = {k.id: k.session for k in kfs[:n]}
        for k in kfs[:n - queries]:
            det.add(k)
        samples, loops = [], 0
        for k in kfs[n - queries:n]:
            # a new keyframe has its full maps until the back end has it, and the preparation the
            # tracker made when it became the tracking reference (every keyframe does), not timed here
            q = replace(k, maps=k.frame)
            q.prepared = prepare_reference(q.frame, det.nf_config)
            t0 = time.perf_counter()
            det.add(q)
            loops += len(det.detect(q, [r for r in kmap if r < k.id], group, start_T, kmap))
            samples.append(time.perf_counter() - t0)
        out[str(n)] = {"add_and_detect": timing_stats(samples), "loops": loops, "stats": det.stats.to_dict()}
    return out


def index_timing(kfs: list[Keyframe], config: Config, sizes: list[int], seed: int) -> dict:
    """Descriptor-index query time (votes + top-M) vs number of indexed keyframes; keyframe
    descriptors beyond the rendered ones are noisy copies."""
    det = LoopDetector(config)
    descs = [d for d in (det.extract(k).descriptors.numpy() for k in kfs) if len(d)]
    g = np.random.default_rng(seed)
    lc = config.loop
    out = {}
    for n in sizes:
        index = DescriptorIndex(IndexSettings(lc.retrieval_neighbours, lc.retrieval_min_votes, lc.retrieval_exact_max))
        t0 = time.perf_counter()
        for i in range(n):
            d = descs[i % len(descs)]
            index.add(i, d if i < len(descs) else d + g.normal(0, 4.0, d.shape).astype(np.float32))
        build = time.perf_counter() - t0
        samples = []
        for q in range(20):
            d = descs[q % len(descs)]
            t0 = time.perf_counter()
            index.query(d, None, lc.max_candidates)
            samples.append(time.perf_counter() - t0)
        out[str(n)] = {"query": timing_stats(samples), "build_total_s": build, "descriptors": index.n_descriptors}
    return out


def backend_comparison(kfs: list[Keyframe], obj_T: np.ndarray, config: Config, overlap: float) -> dict:
    out = {}
    for backend in ("opencv", "kornia"):
        cfg = replace(config, loop=replace(config.loop, sift_backend=backend))
        det = LoopDetector(cfg)
        samples, counts = [], []
        for k in kfs:
            t0 = time.perf_counter()
            counts.append(len(det.extract(k)))
            samples.append(time.perf_counter() - t0)
        out[backend] = {"extract": timing_stats(samples), "keypoints_median": float(np.median(counts)),
                        "accuracy": score_episode(kfs, obj_T, cfg, "full", False, overlap)}
    return out


def run(args: argparse.Namespace) -> Path:
    config = load_config(args.config)
    torch.manual_seed(args.seed)
    set_threads(args.threads)
    results: dict = {"settings": {k: v for k, v in vars(args).items() if k not in ("func",)},
                     "config": config.to_dict(), "accuracy": {}}
    first = None
    for obj in args.objects:
        for kind in args.kinds:
            n = args.frames if kind == "tracking" else 3 * args.frames
            kfs, obj_T = simulate_keyframes(obj, kind, n, args.stride, args.seed, config)
            first = first or (kfs, obj_T)
            for mode in args.modes:
                for realistic in (True, False):
                    key = f"{obj}/{kind}/{mode}/{'coverage+gate' if realistic else 'all+no_gate'}"
                    results["accuracy"][key] = r = score_episode(kfs, obj_T, config, mode, realistic, args.overlap)
                    print(f"{key}: {r['keyframes']} kf, revisits {r['true_revisits']}, accepted {r['accepted']}, "
                          f"false {r['false']}, pair recall {r['pair_recall']}, query recall {r['query_recall']}, "
                          f"median {r['detect_time']['median_ms']:.1f} ms", flush=True)
    if first is not None:
        results["backends"] = backend_comparison(*first, config, args.overlap)
        for b, r in results["backends"].items():
            a = r["accuracy"]
            print(f"backend {b}: extract {r['extract']['median_ms']:.1f} ms, {r['keypoints_median']} kp, "
                  f"false {a['false']}, pair recall {a['pair_recall']}", flush=True)
    results["backend"] = {}
    for obj in args.backend_objects:
        for kind in args.backend_kinds:
            n = args.frames if kind == "tracking" else 3 * args.frames
            kfs, obj_T = tracked_keyframes(obj, kind, n, args.seed, config)
            kf_T = torch.as_tensor(obj_T, dtype=torch.float64)[[k.video_index for k in kfs]]
            reach = math.hypot(*config.sensor.shape) * config.sensor.m_per_px
            revisits = true_revisits(kfs, kf_T, args.overlap, reach)
            for gate in (True, False):
                cfg = replace(config, loop=replace(config.loop, consistency=gate))
                key = f"{obj}/{kind}/{'gate' if gate else 'no_gate'}"
                results["backend"][key] = r = score_backend(kfs, obj_T, cfg, revisits)
                print(f"backend {key}: {r['keyframes']} kf / {r['sessions']} sessions, verified {r['verified']}, "
                      f"accepted {r['accepted']}, false {r['false']}, query recall {r['query_recall']}, "
                      f"groups {r['groups']} (largest {r['largest_group']}), gate {r['summary']['loop_gate']}",
                      flush=True)
    if args.sizes or args.index_sizes:
        big = max(args.sizes or [100])  # index timing replicates these keyframes with noise
        kfs, obj_T = simulate_keyframes(args.timing_object, "long", max(10000, big * args.stride * 2), args.stride,
                                        args.seed, config, max_keyframes=big)
        results["detect_timing"] = timing_vs_size(kfs, obj_T, config, args.sizes, args.queries)
        for n, r in results["detect_timing"].items():
            print(f"map {n}: add+detect median {r['add_and_detect']['median_ms']:.1f} ms", flush=True)
        results["index_timing"] = index_timing(kfs, config, args.index_sizes, args.seed)
        for n, r in results["index_timing"].items():
            print(f"index {n}: query median {r['query']['median_ms']:.2f} ms", flush=True)
    return write_json(args.out, "loops", results)
