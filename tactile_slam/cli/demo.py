"""``tactile-slam demo``: the main job on a bundled default that needs no download."""

from __future__ import annotations

import json
import math
from pathlib import Path

import cv2
import numpy as np
import torch

from tactile_slam.calibration.model import GradientDecoder, load_model
from tactile_slam.config import Config, gelsight_mini_data
from tactile_slam.cli.arguments import output_folder
from tactile_slam.cli.eval import evaluate_run
from tactile_slam.eval.tracking_metrics import pose_vector
from tactile_slam.eval.trajectory import relative_to
from tactile_slam.geometry.frame import FrameBuilder
from tactile_slam.io.dispatch import open_source
from tactile_slam.pipeline.offline import OfflinePipeline, RunOptions
from tactile_slam.sim.episode import DEFAULT_COLOUR_MODEL, SimulationSettings, read_episode, simulate_episode
from tactile_slam.viz import frame_panel, trajectory_report


def register(sub) -> None:
    p = sub.add_parser("demo", help="simulate a short scan, run tactile SLAM on it and evaluate against ground truth")
    p.add_argument("--out", default="outputs/demo", type=output_folder, help="output folder")
    p.add_argument("--frames", type=int, default=250, help="frames of the simulated scan")
    p.add_argument("--object", default="seed", help="simulated object")
    p.add_argument("--seed", type=int, default=1, help="simulation seed")
    p.set_defaults(func=run)


def synthetic_ball_gradients(cfg: Config, diameter_mm: float = 6.31, depth_mm: float = 0.8) -> torch.Tensor:
    """Analytic slopes of a ball pressed into the gel at the image centre, ``(1, H, W, 2)``."""
    h, w = cfg.sensor.shape
    big_r = diameter_mm / cfg.sensor.mm_per_px / 2
    depth = depth_mm / cfg.sensor.mm_per_px
    r = torch.arange(h, dtype=torch.float64)[:, None] - (h - 1) / 2
    c = torch.arange(w, dtype=torch.float64)[None, :] - (w - 1) / 2
    z = torch.sqrt(torch.clamp(big_r**2 - r**2 - c**2, min=0.0)) - (big_r - depth)
    height = -torch.clamp(z, min=0.0)
    gy, gx = torch.gradient(height, dim=(0, 1))
    return torch.stack([gx, gy], dim=-1)[None].float()


def geometry_demo(out: Path) -> dict:
    """Frame geometry on a synthetic ball press and, when present, the real presses."""
    cfg = Config()
    summary: dict = {}
    frame = FrameBuilder(cfg).from_gradients(synthetic_ball_gradients(cfg))
    cv2.imwrite(str(out / "geometry_synthetic_ball.png"), frame_panel(frame))
    summary["synthetic_ball"] = {
        "true_depth_mm": 0.8,
        "depth_mm": round(-float(frame.height.min()) * cfg.sensor.mm_per_px, 4),
        "contact_px": int(frame.contact.sum()),
    }
    calib = gelsight_mini_data() / "calibration"
    if (calib / "background.png").is_file():
        model_path = cfg.sensor.resolved_model_path() or gelsight_mini_data() / "reference_model" / "nnmodel.pth"
        model, _ = load_model(model_path)
        bg = torch.from_numpy(cv2.imread(str(calib / "background.png"))).float()
        builder = FrameBuilder(cfg, GradientDecoder(model, bg, cfg.contact.mlp_skip_color_dist))
        found = sorted(calib.glob("*mm/*/gelsight.png"))
        presses = found[:: max(1, math.ceil(len(found) / 4))]
        for p in presses:
            img = cv2.imread(str(p))
            f = builder.from_bgr(torch.from_numpy(img)[None])
            name = f"{p.parent.parent.name}_{p.parent.name}"
            cv2.imwrite(str(out / f"geometry_press_{name}.png"), frame_panel(f, bgr=img))
            summary[f"press_{name}"] = {
                "model": str(model_path),
                "depth_mm": round(-float(f.height.min()) * cfg.sensor.mm_per_px, 4),
                "contact_px": int(f.contact.sum()),
            }
    return summary


def slam_demo(out: Path, obj: str, frames: int, seed: int) -> dict:
    """Simulate a scan with contact losses, run the full system on its video, evaluate."""
    cfg = Config()
    image_level = cfg.sensor.resolved_model_path() is not None and DEFAULT_COLOUR_MODEL.is_file()
    level = "image" if image_level else "gradients"
    episode = simulate_episode(out / "episode", SimulationSettings(object=obj, kind="contact_loss", seed=seed,
                                                                   frames=frames, level=level), cfg)
    source = open_source(episode, cfg)
    result = OfflinePipeline(source, cfg, out / "run", RunOptions(method="gelslam")).run()
    metrics, series = evaluate_run(out / "run", episode, recon=False)
    (out / "run" / "metrics.json").write_text(json.dumps(metrics, indent=2))
    ep = read_episode(episode)
    ref = metrics["reference_frame"]
    est = np.load(out / "run" / "poses.npy")[ref:]
    gt = relative_to(ep.object_T_sensor, ref)[ref:]
    est_v, gt_v = pose_vector(est), pose_vector(gt)
    est_v[~ep.in_contact[ref:]] = np.nan
    trajectory_report(out / "run" / "report.png", series["frames"], est_v, gt_v, cfg.sensor.fps,
                      f"{obj} scan ({level} level): tactile-slam vs ground truth")
    mae = metrics["tracking"]["per_axis_mae"]
    return {"input_level": level, "episode": str(episode), "run": str(out / "run"),
            "stats": {k: result.stats.get(k) for k in ("frames", "contact_frames", "keyframes", "sessions",
                                                        "loops", "groups", "frames_with_pose", "fps")}
            | {"loops_pending": (result.stats.get("loop_gate") or {}).get("pending", 0)},
            "per_axis_mae": mae}


def run(args) -> int:
    out = Path(args.out)
    (out / "geometry").mkdir(parents=True, exist_ok=True)
    summary = {"slam": slam_demo(out, args.object, args.frames, args.seed),
               "geometry": geometry_demo(out / "geometry")}
    (out / "summary.json").write_text(json.dumps(summary, indent=2))
    s, mae = summary["slam"]["stats"], summary["slam"]["per_axis_mae"]
    print(f"demo: simulated {s['frames']} frames of a {args.object} scan ({summary['slam']['input_level']} level), "
          f"{s['sessions']} sessions, {s['keyframes']} keyframes, {s['loops']} loops "
          f"({s['loops_pending']} verified but waiting for an agreeing loop) -> {s['groups']} group(s)")
    print("demo: per-axis MAE " + ", ".join(f"{k} {mae[k]:.3f}" for k in
                                            ("x_mm", "y_mm", "z_mm", "rx_deg", "ry_deg", "rz_deg")))
    print(f"demo: outputs in {out}/run (poses, mesh, report.png), geometry pictures in {out}/geometry")
    return 0
