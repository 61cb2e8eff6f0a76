"""Registration accuracy and speed: NormalFlow (single, batched, variants) vs ICP and FPFH+RANSAC+ICP.

Pairs come from the simulator: each object is touched once (the reference) and the
sensor is then moved by a controlled ``tar_T_ref`` (translations 0.1-3 mm, in-plane
rotations 0.5-40 deg, tilts up to 15 deg about the gel centre), every pair starting
from the identity. Accuracy is the geodesic rotation error (deg) and the translation
error (mm) against the known motion; a pair is "wrong" when either exceeds
``--wrong-deg`` / ``--wrong-mm``; "rejected" when the method reports failure; "false
accept" when it is wrong but not rejected. Times are wall-clock per call on the chosen
device, after warm-up; the NormalFlow variants take turns pair by pair so that a drift of
the machine's speed does not favour one. The speed-accuracy trade sweeps ``n_samples``
and the iteration cap.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import torch

from tactile_slam.bench.common import set_threads, time_fn, timing_stats, write_json
from tactile_slam.cli.arguments import positive_int
from tactile_slam.cli.devices import add_device_argument
from tactile_slam.config import Config, NormalFlowConfig
from tactile_slam.geometry.frame import Frame, FrameBuilder
from tactile_slam.registration.baselines import register_fpfh, register_icp
from tactile_slam.registration.normalflow import prepare_reference, register, register_prepared
from tactile_slam.registration.result import RegistrationResult, pose_error

OBJECTS = ("seed", "shell", "dice", "lime", "handle")  # handle: low texture
TRANSLATIONS_MM = (0.1, 0.5, 1.0, 2.0, 3.0)
ROTATIONS_DEG = (0.5, 2.0, 5.0, 10.0, 20.0, 40.0)
TILTS_DEG = (2.0, 5.0, 10.0, 15.0)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--objects", nargs="+", default=list(OBJECTS), help="simulator objects")
    add_device_argument(p)
    p.add_argument("--threads", type=positive_int, default=None, help="torch CPU threads (default: torch's choice)")
    p.add_argument("--depth-mm", type=float, default=0.8, help="reference indentation")
    p.add_argument("--repeats", type=positive_int, default=5, help="timed calls per pair")
    p.add_argument("--fpfh-pairs", type=int, default=3,
                   help="pairs per object for FPFH+RANSAC+ICP (slow; 0 skips it)")
    p.add_argument("--wrong-deg", type=float, default=1.0)
    p.add_argument("--wrong-mm", type=float, default=0.1)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--png", default=None, help="plot path (default: the JSON path with .png)")


def motions(rng: np.random.Generator) -> list[tuple[str, torch.Tensor]]:
    """Controlled ``tar_T_ref`` (float64, metres) with their labels."""
    from scipy.spatial.transform import Rotation

    out = []
    for t in TRANSLATIONS_MM:
        a = rng.uniform(0, 2 * np.pi)
        T = np.eye(4)
        T[:2, 3] = t * 1e-3 * np.array([np.cos(a), np.sin(a)])
        out.append((f"translate {t} mm", T))
    for r in ROTATIONS_DEG:
        T = np.eye(4)
        T[:3, :3] = Rotation.from_euler("z", r * rng.choice([-1, 1]), degrees=True).as_matrix()
        out.append((f"rotate z {r} deg", T))
    for r in TILTS_DEG:
        a = rng.uniform(0, 2 * np.pi)
        T = np.eye(4)
        T[:3, :3] = Rotation.from_rotvec(np.deg2rad(r) * np.array([np.cos(a), np.sin(a), 0.0])).as_matrix()
        out.append((f"tilt {r} deg", T))
    return [(name, torch.from_numpy(T)) for name, T in out]


def make_pairs(obj: str, depth_mm: float, rng: np.random.Generator, cfg: Config):
    """``(ref (B=1), tars (B=N), truth (N, 4, 4), labels)`` for one simulator object."""
    from tactile_slam.sim.motions import pressed_poses
    from tactile_slam.sim.objects import make_object
    from tactile_slam.sim.renderer import GelRenderer

    mesh = make_object(obj)
    renderer = GelRenderer(mesh, cfg)
    verts, normals = np.asarray(mesh.vertices), np.asarray(mesh.vertex_normals)
    top = np.argmax(verts @ np.array([0.3, 0.2, 1.0]))  # a touch on the upper side, off any symmetry axis
    hint = np.array([[1.0, 0.0, 0.0]])
    zero = np.zeros(1)
    object_T_ref = pressed_poses(renderer, verts[top:top + 1], normals[top:top + 1], hint, zero, zero, zero,
                                 np.array([depth_mm * 1e-3]))[0]
    labelled = motions(rng)
    truth = torch.stack([T for _, T in labelled])
    # object_T_tar = object_T_ref inv(M) gives tar_T_ref = M
    poses = np.concatenate([object_T_ref[None], object_T_ref[None] @ np.linalg.inv(truth.numpy())])
    maps = renderer.render(poses)
    frames = FrameBuilder(cfg).from_gradients(maps.gradients, maps.contact)
    return frames[0], frames[1:], truth, [name for name, _ in labelled]


def summarise(res: RegistrationResult, truth: torch.Tensor, args) -> dict:
    rot, trans = pose_error(res.tar_T_ref.cpu(), truth)
    wrong = (rot > args.wrong_deg) | (trans > args.wrong_mm)
    ok = res.ok.cpu()
    return {
        "rot_err_deg_median": float(rot.median()), "rot_err_deg_mean": float(rot.mean()),
        "trans_err_mm_median": float(trans.median()), "trans_err_mm_mean": float(trans.mean()),
        "wrong_rate": float(wrong.double().mean()), "rejected_rate": float((~ok).double().mean()),
        "false_accept_rate": float((wrong & ok).double().mean()), "n_pairs": int(len(rot)),
        "per_pair": {"rot_err_deg": rot.tolist(), "trans_err_mm": trans.tolist(), "ok": ok.tolist()},
    }


def _timed_nf(refs: list[Frame], tars: list[Frame], configs: dict[str, NormalFlowConfig], repeats: int,
              sync: bool) -> dict[str, tuple[RegistrationResult, list[float], list[float]]]:
    """Per-pair results and per-call time samples of single-pair NormalFlow for each
    configuration: ``(results, register times (preparation included), times against an
    already prepared reference (the tracking case: one keyframe, many frames))``. The
    configurations take turns pair by pair, so a drift of the machine's speed during
    the run (several percent on this one) does not favour whichever runs later."""
    out = {name: ([], [], []) for name in configs}
    for ref, tar in zip(refs, tars):
        for name, cfg in configs.items():
            results, samples, prepared = out[name]
            results.append(register(ref, tar, None, cfg))
            samples += time_fn(lambda: register(ref, tar, None, cfg), repeats, warmup=1, sync_cuda=sync)
            prep = prepare_reference(ref, cfg)
            prepared += time_fn(lambda: register_prepared(prep, tar, None, cfg), repeats, warmup=1, sync_cuda=sync)
    return {name: (RegistrationResult.cat(r), s, p) for name, (r, s, p) in out.items()}


def run(args) -> Path:
    if args.fpfh_pairs < 0 or args.repeats < 1:
        raise ValueError(f"--fpfh-pairs must be >= 0 and --repeats >= 1, got {args.fpfh_pairs}, {args.repeats}")
    set_threads(args.threads)
    cfg = Config()
    rng = np.random.default_rng(args.seed)
    dev = torch.device(args.device)
    sync = dev.type == "cuda"
    t0 = time.perf_counter()
    data = {obj: make_pairs(obj, args.depth_mm, rng, cfg) for obj in args.objects}
    render_s = time.perf_counter() - t0
    labels = data[args.objects[0]][3]
    refs = [data[o][0].to(dev) for o in args.objects for _ in range(len(data[o][3]))]
    tars = [data[o][1][i].to(dev) for o in args.objects for i in range(len(data[o][3]))]
    truth = torch.cat([data[o][2] for o in args.objects])
    obj_of = [o for o in args.objects for _ in range(len(data[o][3]))]

    variants = {
        "normalflow": NormalFlowConfig(),
        "normalflow_topk (global top-k samples, the default until 2026-11-29)": NormalFlowConfig(selection="topk"),
        "normalflow_coarse4": NormalFlowConfig(coarse_factors=(4,)),
        "normalflow_fallback16-4": NormalFlowConfig(fallback_factors=(16, 4)),
        "normalflow_fallback16-4_noshift": NormalFlowConfig(fallback_factors=(16, 4), fallback_shift_search=False),
        "normalflow_min7 (reference's >= 7 iterations)": NormalFlowConfig(min_iters=7),
        "normalflow_no_stall_check (stall_check_iters=0)": NormalFlowConfig(stall_check_iters=0),
        "threshold_rule (public GelSLAM selection)": NormalFlowConfig(selection="threshold", min_iters=7),
        "old_normalflow (random 5000, no checks)": NormalFlowConfig(selection="random", n_samples=5000,
                                                                    check_scores=False, min_iters=7),
    }
    methods: dict = {}
    for name, (res, samples, prepared) in _timed_nf(refs, tars, variants, args.repeats, sync).items():
        methods[name] = {"time_per_pair": timing_stats(samples), "time_per_pair_prepared": timing_stats(prepared),
                         "all": summarise(res, truth, args),
                         "per_object": {o: summarise(res[torch.tensor([x == o for x in obj_of])],
                                                     truth[torch.tensor([x == o for x in obj_of])], args)
                                        for o in args.objects}}

    # batched NormalFlow: B pairs (each with its own reference) per call
    batched = {}
    n = len(refs)
    for b in (1, 8, 64):
        idx = [i % n for i in range(b)]
        ref_b, tar_b = Frame.cat([refs[i] for i in idx]), Frame.cat([tars[i] for i in idx])
        res_b = register(ref_b, tar_b)
        st = timing_stats(time_fn(lambda: register(ref_b, tar_b), args.repeats * 2, warmup=1, sync_cuda=sync))
        single = register(refs[idx[-1]], tars[idx[-1]])
        rot_diff, trans_diff = pose_error(res_b.tar_T_ref[-1:].cpu(), single.tar_T_ref.cpu())
        batched[f"B={b}"] = st | {"median_ms_per_pair": st["median_ms"] / b,
                                  "max_rot_diff_vs_single_deg": float(rot_diff.max()),
                                  "max_trans_diff_vs_single_mm": float(trans_diff.max())}
    # the same 64 pairs without the stall check (and on the CPU as one piece, without the
    # cache-sized chunks), alternating with the default so a drift of the machine favours neither
    others = {"no stall check (stall_check_iters=0)": NormalFlowConfig(stall_check_iters=0)}
    if dev.type == "cpu":
        others["whole batch (cpu_chunk_samples=0)"] = NormalFlowConfig(cpu_chunk_samples=0)
    samples = {name: [] for name in ["default", *others]}
    for _ in range(args.repeats * 2):
        samples["default"] += time_fn(lambda: register(ref_b, tar_b), 1, warmup=0, sync_cuda=sync)
        for name, cfg_o in others.items():
            samples[name] += time_fn(lambda: register(ref_b, tar_b, None, cfg_o), 1, warmup=0, sync_cuda=sync)
    for name, st in samples.items():
        batched[f"B=64, alternating: {name}"] = timing_stats(st)
    batched["B=64, iterations summed: default, no stall check"] = [  # res_b: the default's B=64 result
        int(res_b.iterations.sum()),
        int(register(ref_b, tar_b, None, others["no stall check (stall_check_iters=0)"]).iterations.sum())]
    # one reference, 64 targets (a keyframe against many frames): the object's own pairs
    own = [i for i in range(n) if obj_of[i] == args.objects[0]]
    tar_1 = Frame.cat([tars[own[i % len(own)]] for i in range(64)])
    st = timing_stats(time_fn(lambda: register(refs[own[0]], tar_1), args.repeats * 2, warmup=1, sync_cuda=sync))
    batched["B=64, one reference"] = st | {"median_ms_per_pair": st["median_ms"] / 64}

    # Open3D baselines (CPU)
    cpu_refs, cpu_tars = [r.to("cpu") for r in refs], [t.to("cpu") for t in tars]
    spread = []  # FPFH is slow: a few pairs per object, spread over the motion list
    for o in args.objects:
        own = [j for j in range(n) if obj_of[j] == o]
        spread += [own[k] for k in np.unique(np.linspace(0, len(own) - 1, args.fpfh_pairs).round().astype(int))]
    for name, fn, pick in (("icp_point_to_plane", register_icp, range(n)), ("fpfh_ransac_icp", register_fpfh, spread)):
        pick = list(pick)
        if not pick:  # --fpfh-pairs 0
            continue
        results, samples = [], []
        for i in pick:
            t1 = time.perf_counter()
            results.append(fn(cpu_refs[i], cpu_tars[i]))
            samples.append(time.perf_counter() - t1)
        res = RegistrationResult.cat(results)
        sel = {o: torch.tensor([obj_of[i] == o for i in pick]) for o in args.objects}
        methods[name] = {"time_per_pair": timing_stats(samples), "all": summarise(res, truth[pick], args),
                         "per_object": {o: summarise(res[m], truth[pick][m], args) for o, m in sel.items() if m.any()},
                         "pairs": [f"{obj_of[i]}: {labels[i % len(labels)]}" for i in pick]}
        nf = methods["normalflow"]["all"]["per_pair"]
        methods[name]["normalflow_on_same_pairs"] = {
            "rot_err_deg_median": float(np.median([nf["rot_err_deg"][i] for i in pick])),
            "trans_err_mm_median": float(np.median([nf["trans_err_mm"][i] for i in pick])),
        }

    # speed-accuracy trade: n_samples x iteration cap
    sweep = []
    for n_samples in (250, 500, 1000, 3000, None):
        for cap in (10, 20, 50):
            c = NormalFlowConfig(n_samples=n_samples, max_iters=cap)
            res, samples, _ = _timed_nf(refs, tars, {"sweep": c}, max(args.repeats // 2, 1), sync)["sweep"]
            s = summarise(res, truth, args)
            s.pop("per_pair")
            sweep.append({"n_samples": n_samples or "all", "max_iters": cap,
                          "median_ms": timing_stats(samples)["median_ms"]} | s)

    results = {"device": args.device, "objects": args.objects, "motions": labels, "render_s": render_s,
               "thresholds": {"wrong_deg": args.wrong_deg, "wrong_mm": args.wrong_mm},
               "methods": methods, "batched_normalflow": batched, "sweep": sweep}
    out = write_json(args.out, "registration", results)
    _plot(results, Path(args.png) if args.png else out.with_suffix(".png"))
    return out


def _plot(results: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(12, 4.5))
    ax = axes[0]
    for cap, marker in ((10, "o"), (20, "s"), (50, "^")):
        pts = [s for s in results["sweep"] if s["max_iters"] == cap]
        ax.plot([s["median_ms"] for s in pts], [s["rot_err_deg_median"] for s in pts], marker=marker,
                label=f"max_iters {cap}")
        for s in pts:
            ax.annotate(str(s["n_samples"]), (s["median_ms"], s["rot_err_deg_median"]), fontsize=7)
    ax.set_xlabel("median time per pair (ms)")
    ax.set_ylabel("median rotation error (deg)")
    ax.set_title("NormalFlow: n_samples x iteration cap")
    ax.legend()
    ax = axes[1]
    for name, m in results["methods"].items():
        ax.scatter(m["time_per_pair"]["median_ms"], m["all"]["wrong_rate"], label=name)
    ax.set_xscale("log")
    ax.set_xlabel("median time per pair (ms, log)")
    ax.set_ylabel(f"wrong rate (> {results['thresholds']['wrong_deg']} deg or {results['thresholds']['wrong_mm']} mm)")
    ax.set_title("methods")
    ax.legend(fontsize=7)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
