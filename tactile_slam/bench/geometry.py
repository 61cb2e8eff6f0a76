"""Time from a BGR frame to the geometry tracking needs (gradients, height, contact, normals, curvature)."""

from __future__ import annotations

import argparse
from pathlib import Path

import cv2
import numpy as np
import torch

from tactile_slam.bench.common import time_fn, timing_stats, write_json
from tactile_slam.calibration.model import GradientDecoder, load_model
from tactile_slam.cli.arguments import positive_int
from tactile_slam.cli.devices import add_device_argument
from tactile_slam.config import Config, gelsight_mini_data
from tactile_slam.geometry.contact import colour_distance, colour_mask, contact_mask, zero_level
from tactile_slam.geometry.curvature import curvature, normals_from_gradients
from tactile_slam.geometry.frame import FrameBuilder
from tactile_slam.geometry.morphology import dilate
from tactile_slam.geometry.poisson import integrate_exact


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--data", default=str(gelsight_mini_data()), help="GelSight Mini data folder (calibration presses)")
    p.add_argument("--model", default=None,
                   help="calibration model (default: models/gelsight_mini.pt, else the reference model)")
    p.add_argument("--frames", type=positive_int, default=200, help="timed frames per setting")
    add_device_argument(p)


def _load(args) -> tuple[Config, GradientDecoder, torch.Tensor]:
    data = Path(args.data)
    calib = data / "calibration"
    if not (calib / "background.png").is_file():
        raise FileNotFoundError(f"no calibration presses under {calib}; pass --data")
    cfg = Config()
    model_path = args.model or cfg.sensor.resolved_model_path() or data / "reference_model" / "nnmodel.pth"
    model, _ = load_model(model_path, args.device)
    bg = torch.from_numpy(cv2.imread(str(calib / "background.png"))).float()
    images = [cv2.imread(str(p)) for p in sorted(calib.glob("*mm/*/gelsight.png"))]
    return cfg, GradientDecoder(model, bg, cfg.contact.mlp_skip_color_dist), torch.from_numpy(np.stack(images))


def run(args) -> Path:
    cfg, decoder, images = _load(args)
    images = images.to(args.device)
    builder = FrameBuilder(cfg, decoder)
    sync = args.device.startswith("cuda")
    n = len(images)
    results: dict = {"device": args.device, "image_size": list(cfg.sensor.shape),
                     "model_hidden": list(decoder.model.hidden)}

    counter = iter(range(10**9))
    single = time_fn(lambda: builder.from_bgr(images[next(counter) % n][None]), args.frames, sync_cuda=sync)
    results["single_frame"] = timing_stats(single)
    b = 16
    reps = max(args.frames // b, 13)
    batch = time_fn(lambda: builder.from_bgr(images[torch.arange(b) % n]), reps, sync_cuda=sync)
    st = timing_stats(batch)
    results["batch16"] = st | {"median_ms_per_frame": st["median_ms"] / b}

    # per-stage breakdown on single frames
    img = images[5][None]
    dist = colour_distance(img, decoder.background)
    changed = dilate(dist > cfg.contact.mlp_skip_color_dist, 5)
    stages = {}
    stages["decode_mlp"] = time_fn(lambda: decoder(img, changed=changed), args.frames // 2, sync_cuda=sync)
    g = decoder(img, changed=changed)
    stages["poisson"] = time_fn(lambda: integrate_exact(g), args.frames // 2, sync_cuda=sync)
    col = colour_mask(dist, cfg.contact.color_dist_threshold, cfg.contact.dilate, cfg.contact.erode)
    h = zero_level(integrate_exact(g), dilate(col, cfg.contact.dilate))

    def masks():
        c = colour_mask(colour_distance(img, decoder.background), cfg.contact.color_dist_threshold,
                        cfg.contact.dilate, cfg.contact.erode)
        zero_level(h, dilate(c, cfg.contact.dilate))
        threshold, fraction, floor = cfg.depth_test
        return contact_mask(h, c, threshold, cfg.contact.height_percentile, cfg.final_erode_px, fraction, floor)

    stages["masks_zero_level"] = time_fn(masks, args.frames // 2, sync_cuda=sync)
    m = masks()[1]
    stages["curvature_normals"] = time_fn(lambda: (curvature(g, m), normals_from_gradients(g)), args.frames // 2,
                                          sync_cuda=sync)
    results["stages"] = {k: timing_stats(v) for k, v in stages.items()}
    results["mlp_pixels_fraction"] = float(changed.float().mean())
    out = write_json(args.out, "geometry", results)
    print(f"geometry: single {results['single_frame']['median_ms']:.2f} ms, "
          f"batch16 {results['batch16']['median_ms_per_frame']:.2f} ms/frame -> {out}")
    return out
