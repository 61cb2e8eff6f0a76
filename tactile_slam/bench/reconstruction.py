"""Reconstruction accuracy (CD, F-score, NCD) and fusion/meshing time on simulated scans.

For each object and size (the paper's Table VI objects at its small and large print
sizes) a hand-held scan is simulated with :mod:`tactile_slam.sim`, keyframes are taken
every ``--stride`` in-contact frames, and :func:`tactile_slam.recon.reconstruct` runs
with the ground-truth poses (``start`` = the first keyframe). Both the fused grid mesh
and the Poisson mesh are scored with :func:`tactile_slam.eval.recon_metrics.recon_report`
(ground-truth placement, and after ICP), for each fusion gate in ``--gates``.
"""

from __future__ import annotations

import time

import numpy as np
import torch
from scipy.spatial.transform import Rotation

from tactile_slam.bench.common import write_json
from tactile_slam.config import Config
from tactile_slam.eval.recon_metrics import recon_report, touch_poses
from tactile_slam.geometry.frame import FrameBuilder
from tactile_slam.recon import reconstruct
from tactile_slam.sim.motions import make_motion
from tactile_slam.sim.objects import make_object
from tactile_slam.sim.renderer import GelRenderer
from tactile_slam.tracking.keyframe import Keyframe

# The paper's Table VI sizes (mm) of the small and large prints.
SIZES_MM = {"seed": (9.5, 14.3), "shell": (18.4, 27.6), "dice": (10.0, 15.0), "lime": (15.0, 29.9)}


def add_arguments(parser) -> None:
    parser.add_argument("--objects", nargs="+", default=list(SIZES_MM), choices=sorted(SIZES_MM))
    parser.add_argument("--sizes", nargs="+", default=["small", "large"], choices=["small", "large"])
    parser.add_argument("--frames", type=int, default=3000, help="simulated scan frames per object")
    parser.add_argument("--stride", type=int, default=5, help="keyframe every N in-contact frames")
    parser.add_argument("--gates", type=float, nargs="+", default=[3.0, 1.0, 0.5], help="fusion gates, mm")
    parser.add_argument("--samples", type=int, default=100_000, help="surface samples for CD/F-score")
    parser.add_argument("--touches", type=int, default=100, help="NCD touches")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--partial", action="store_true", help="trim the Poisson mesh (watertight=False)")
    parser.add_argument("--timing", type=int, default=0, metavar="N",
                        help="instead: time fusion + meshing of N touches spread over a 120 mm lime")
    parser.add_argument("--noise", type=float, nargs=2, default=[0.0, 0.0], metavar=("MM", "DEG"),
                        help="perturb keyframe poses by Gaussian noise (std per axis) to mimic estimated poses")


def simulated_keyframes(name: str, size_mm: float, frames: int, stride: int, seed: int, config: Config):
    """Render a scan; return (gt mesh, keyframes, ``(K, 4, 4)`` object_T_sensor)."""
    mesh = make_object(name, size_mm, seed)
    renderer = GelRenderer(mesh, config)
    motion = make_motion(renderer, "scan", frames, seed)
    builder = FrameBuilder(config)
    kfs, poses = [], []
    count = 0
    batch = 32
    for a in range(0, len(motion.object_T_sensor), batch):
        sel = np.flatnonzero(motion.pressed[a:a + batch]) + a
        if len(sel) == 0:
            continue
        maps = renderer.render(motion.object_T_sensor[sel])
        for j, i in enumerate(sel):
            if not bool(maps.in_contact[j]):
                continue
            if count % stride == 0:
                frame = builder.from_gradients(maps.gradients[j:j + 1], contact=maps.contact[j:j + 1],
                                               index=torch.tensor([int(i)]))
                kfs.append(Keyframe(id=len(kfs), session=0, frame=frame, new_session=not kfs,
                                    prev_T_kf=torch.eye(4, dtype=torch.float64)))
                poses.append(motion.object_T_sensor[i])
            count += 1
    return mesh, kfs, np.stack(poses)


def perturb(o_T_s: np.ndarray, noise_mm: float, noise_deg: float, seed: int) -> np.ndarray:
    """Right-multiply poses 1.. by random small motions (std per axis); pose 0 is kept."""
    if noise_mm == 0 and noise_deg == 0:
        return o_T_s
    rng = np.random.default_rng(seed + 1)
    out = o_T_s.copy()
    for k in range(1, len(out)):
        d = np.eye(4)
        d[:3, :3] = Rotation.from_rotvec(np.radians(noise_deg) * rng.normal(size=3)).as_matrix()
        d[:3, 3] = noise_mm * 1e-3 * rng.normal(size=3)
        out[k] = out[k] @ d
    return out


def timing_run(n_touches: int, seed: int, config: Config) -> dict:
    """Fusion + meshing time for ``n_touches`` shallow presses (0.3 mm) at farthest-point
    locations of a 120 mm lime: large enough that most touches stay coverage keyframes."""
    gt = make_object("lime", 120.0, seed)
    renderer = GelRenderer(gt, config)
    o_T_s = touch_poses(gt, n_touches, depth_mm=0.3, seed=seed, config=config, renderer=renderer)
    builder = FrameBuilder(config)
    kfs, poses = [], []
    for a in range(0, len(o_T_s), 32):
        maps = renderer.render(o_T_s[a:a + 32])
        for j in range(len(maps.contact)):
            if bool(maps.contact[j].any()):
                frame = builder.from_gradients(maps.gradients[j:j + 1], contact=maps.contact[j:j + 1])
                kfs.append(Keyframe(id=len(kfs), session=0, frame=frame, new_session=not kfs,
                                    prev_T_kf=torch.eye(4, dtype=torch.float64)))
                poses.append(o_T_s[a + j])
    o_T_s = np.stack(poses)
    t0 = time.perf_counter()
    res = reconstruct(kfs, torch.from_numpy(np.linalg.inv(o_T_s[0]) @ o_T_s), config)
    total = time.perf_counter() - t0
    out = {"touches": n_touches, "keyframes": len(kfs), "total_s": total, "stats": res.stats}
    print(f"timing: {len(kfs)} keyframes, {res.stats['coverage_keyframes']} coverage keyframes: coverage "
          f"{res.stats['coverage_s']:.1f} s, fusion {res.stats['fusion_s']:.1f} s, meshing "
          f"{res.stats['meshing_s']:.1f} s, total {total:.1f} s", flush=True)
    return out


def run(args):
    config = Config()
    config.recon.watertight = not args.partial
    if args.timing:
        return write_json(args.out, "reconstruction", {"settings": vars(args) | {"func": None},
                                                       "timing": timing_run(args.timing, args.seed, config)})
    results = []
    for name in args.objects:
        for size_label in args.sizes:
            size = SIZES_MM[name][0 if size_label == "small" else 1]
            t0 = time.perf_counter()
            gt, kfs, o_T_s = simulated_keyframes(name, size, args.frames, args.stride, args.seed, config)
            sim_s = time.perf_counter() - t0
            start_T_kf = torch.from_numpy(np.linalg.inv(o_T_s[0]) @ perturb(o_T_s, *args.noise, args.seed))
            for gate in args.gates:
                config.recon.fusion_gate_mm = gate
                res = reconstruct(kfs, start_T_kf, config)
                entry = {"object": name, "size": size_label, "size_mm": size, "gate_mm": gate,
                         "keyframes": len(kfs), "simulation_s": sim_s,
                         "poses": "ground truth" if args.noise == [0.0, 0.0] else f"noisy {args.noise} mm/deg",
                         "stats": res.stats}
                for label, mesh in (("fused", res.fused_mesh), ("mesh", res.mesh)):
                    rep = recon_report(mesh.to_open3d(), gt, o_T_s[0], icp=True, n_samples=args.samples,
                                       n_touches=args.touches, seed=args.seed, config=config)
                    entry[label] = rep
                print(_line(entry), flush=True)
                results.append(entry)
                # rewritten after every run so a long benchmark leaves partial results
                path = write_json(args.out, "reconstruction", {"settings": vars(args) | {"func": None},
                                                                "runs": results})
    return path


def _line(e: dict) -> str:
    m = e["mesh"]
    return (f"{e['object']:6s} {e['size']:5s} gate {e['gate_mm']:.1f} mm  K {e['keyframes']:4d} "
            f"cov {e['stats']['coverage_keyframes']:4d}  fused CD {e['fused']['gt_pose']['chamfer_mm']:.3f} "
            f"mesh CD {m['gt_pose']['chamfer_mm']:.3f} / ICP {m['icp']['chamfer_mm']:.3f} mm  "
            f"NCD {m['gt_pose']['ncd']:.3f} / {m['icp']['ncd']:.3f}  "
            f"fusion {e['stats']['coverage_s'] + e['stats']['fusion_s']:.1f} s meshing {e['stats']['meshing_s']:.1f} s")
