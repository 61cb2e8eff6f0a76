"""``tactile-slam demo``: the main job on a bundled default that needs no download."""

from __future__ import annotations

import json
import math
from pathlib import Path

import cv2
import torch

from tactile_slam.calibration.model import GradientDecoder, load_model
from tactile_slam.config import REPO_ROOT, Config
from tactile_slam.geometry.frame import FrameBuilder
from tactile_slam.viz import frame_panel

SHARED_MINI = REPO_ROOT.parent / "shared" / "data" / "gelsight_mini"


def register(sub) -> None:
    p = sub.add_parser("demo", help="run the main job on a bundled default and write pictures and results")
    p.add_argument("--out", default="outputs/demo", help="output folder")
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
    calib = SHARED_MINI / "calibration"
    if (calib / "background.png").is_file():
        model_path = cfg.sensor.resolved_model_path() or SHARED_MINI / "reference_model" / "nnmodel.pth"
        model, _ = load_model(model_path)
        bg = torch.from_numpy(cv2.imread(str(calib / "background.png"))).float()
        builder = FrameBuilder(cfg, GradientDecoder(model, bg, cfg.contact.mlp_skip_color_dist))
        presses = sorted(calib.glob("*mm/*/gelsight.png"))[:: max(1, math.ceil(len(list(calib.glob("*mm/*/gelsight.png"))) / 4))]
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


def run(args) -> int:
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    summary = geometry_demo(out)
    (out / "summary.json").write_text(json.dumps(summary, indent=2))
    print(f"demo: wrote {len(list(out.glob('*.png')))} pictures and summary.json to {out}")
    for k, v in summary.items():
        print(f"  {k}: {v}")
    return 0
