"""Calibration: accuracy, training time and inference speed per MLP size, beside the SDK model.

For each hidden-size choice and seeded split of a calibration folder: train with the
default recipe, then score the held-out presses (gradient-angle MAE in rad, normal-angle
MAE in degrees) with the reference model on the same presses, and time full-frame
decoding (240x320 -> gradients) of the trained model. ``--split diameter`` holds out one
ball size at a time instead (train on the other sizes' presses, score that size's): how a
model decodes presses of a ball it has never seen.
"""

from __future__ import annotations

import argparse
import statistics
from pathlib import Path

import torch

from tactile_slam.bench.common import set_threads, time_fn, timing_stats, write_json
from tactile_slam.calibration.catalog import load_calibration_set
from tactile_slam.calibration.dataset import build_dataset, split_by_diameter
from tactile_slam.calibration.evaluate import evaluate_model
from tactile_slam.calibration.labels import label_presses
from tactile_slam.calibration.model import GradientDecoder, load_model
from tactile_slam.calibration.train import LOSSES, TrainConfig, train_model
from tactile_slam.cli.arguments import positive_int
from tactile_slam.cli.devices import add_device_argument
from tactile_slam.config import gelsight_mini_data, load_config


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--data", default=str(gelsight_mini_data()),
                   help="folder holding calibration/ and reference_model/nnmodel.pth")
    p.add_argument("--hidden", default="16,16;32,32,32;64,64,64", help="sizes to compare, ';'-separated")
    p.add_argument("--seeds", type=positive_int, default=3, help="seeded splits per size (--split random)")
    p.add_argument("--split", choices=("random", "diameter"), default="random",
                   help="random: seeded 80/20 splits by press; diameter: each ball size held out in turn")
    p.add_argument("--epochs", type=positive_int, default=TrainConfig.epochs)
    p.add_argument("--lr-step", type=positive_int, default=TrainConfig.lr_step)
    p.add_argument("--loss", default=TrainConfig.loss, choices=sorted(LOSSES))
    p.add_argument("--restarts", type=positive_int, default=TrainConfig.restarts,
                   help="models per split (seeds seed, seed+1, ...); the best fit to the training presses is kept")
    add_device_argument(p)
    p.add_argument("--threads", type=positive_int, default=1)
    p.add_argument("--repeats", type=positive_int, default=20, help="timed full-frame decodes per model")


def run(args) -> Path:
    TrainConfig(epochs=args.epochs, lr_step=args.lr_step, loss=args.loss, restarts=args.restarts).validate()
    set_threads(args.threads)
    sensor = load_config("gelsight_mini").sensor
    data_dir = Path(args.data)
    calib = load_calibration_set(data_dir / "calibration", sensor.shape)
    labels = {lb.reldir: lb for lb in label_presses(calib, sensor.mm_per_px, sensor.max_indentation_mm)}
    ref, _ = load_model(data_dir / "reference_model" / "nnmodel.pth", args.device)
    bg = torch.from_numpy(calib.background).to(args.device)
    frame = torch.from_numpy(calib.image(calib.presses[0])).to(args.device)[None]
    sync = args.device.startswith("cuda")
    if args.split == "diameter":
        held_out = sorted({p.diameter_mm for p in calib.presses})
        splits = [build_dataset(calib, labels, sensor.mm_per_px, seed, split=split_by_diameter(calib, d))
                  for seed, d in enumerate(held_out)]
    else:
        held_out = [None] * args.seeds
        splits = [build_dataset(calib, labels, sensor.mm_per_px, seed) for seed in range(args.seeds)]
    ref_evals = [evaluate_model(ref, calib, labels, s.split["test"], sensor.mm_per_px) for s in splits]
    results = {"reference": {
        "angle_mae_rad": statistics.mean(e.angle_mae for e in ref_evals),
        "normal_mae_deg": statistics.mean(e.to_dict()["normal_mae_deg"] for e in ref_evals),
        "decode_frame": timing_stats(time_fn(lambda: GradientDecoder(ref, bg, 0.0)(frame), args.repeats, 2, sync)),
        "by_slope_per_split": [e.to_dict()["by_slope"] for e in ref_evals],
    }}
    for spec in args.hidden.split(";"):
        hidden = tuple(int(h) for h in spec.split(","))
        runs = []
        for seed, data in enumerate(splits):
            cfg = TrainConfig(hidden=hidden, epochs=args.epochs, lr_step=args.lr_step, loss=args.loss, seed=seed,
                              device=args.device, restarts=args.restarts)
            res = train_model(data.train, cfg)
            ev = evaluate_model(res.model, calib, labels, data.split["test"], sensor.mm_per_px)
            runs.append({"seed": seed, "held_out_mm": held_out[seed], "train_presses": len(data.split["train"]),
                         "test_presses": len(data.split["test"]), "train_s": res.seconds, "angle_mae_rad": ev.angle_mae,
                         "normal_mae_deg": ev.to_dict()["normal_mae_deg"],
                         "reference_angle_mae_rad": ref_evals[seed].angle_mae,
                         "reference_normal_mae_deg": ref_evals[seed].to_dict()["normal_mae_deg"],
                         "kept_seed": res.seed, "restarts": res.restarts, "by_slope": ev.to_dict()["by_slope"]})
        decoder = GradientDecoder(res.model, bg, 0.0)
        results["mlp_5-" + "-".join(map(str, hidden)) + "-2"] = {
            "parameters": sum(p.numel() for p in res.model.parameters()),
            "angle_mae_rad": statistics.mean(r["angle_mae_rad"] for r in runs),
            "normal_mae_deg": statistics.mean(r["normal_mae_deg"] for r in runs),
            "train_s_median": statistics.median(r["train_s"] for r in runs),
            "splits_no_worse_than_reference": sum(r["angle_mae_rad"] <= r["reference_angle_mae_rad"] for r in runs),
            "decode_frame": timing_stats(time_fn(lambda: decoder(frame), args.repeats, 2, sync)),
            "runs": runs,
        }
    results["settings"] = {"epochs": args.epochs, "lr_step": args.lr_step, "loss": args.loss, "seeds": args.seeds,
                           "split": args.split,
                           "restarts": args.restarts,
                           "device": args.device, "threads": args.threads}
    return write_json(args.out, "calibration", results)
