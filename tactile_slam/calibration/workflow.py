"""End-to-end calibration runs shared by the CLI and the shipping script:
label -> dataset -> train -> evaluate (beside a reference model) -> files."""

from __future__ import annotations

import json
import math
from dataclasses import asdict
from pathlib import Path
from typing import Any

import torch

from tactile_slam.calibration.catalog import CalibrationSet, load_calibration_set
from tactile_slam.calibration.colour_model import colour_samples, fit_colour_model
from tactile_slam.calibration.dataset import build_dataset
from tactile_slam.calibration.evaluate import evaluate_model, format_comparison, format_slope_gain
from tactile_slam.calibration.labels import (
    PressLabel, label_presses, read_labels, rim_margin_px, write_labels, write_overlays,
)
from tactile_slam.calibration.model import load_model, save_model
from tactile_slam.calibration.train import TrainConfig, train_model, write_training_report
from tactile_slam.config import SensorConfig


ADVISABLE_PRESSES = 50
"""Usable presses (reliable labels, training and held-out together) below which
:func:`run_training` warns: docs/calibration.md advises about 50, spread over the gel."""


def labels_for(calib: CalibrationSet, sensor: SensorConfig, labels_file: str | Path | None = None) -> list[PressLabel]:
    """Labels of every press: from ``labels_file`` where it lists the press, detected otherwise."""
    overrides = read_labels(labels_file) if labels_file is not None else None
    return label_presses(calib, sensor.mm_per_px, sensor.max_indentation_mm, overrides)


def run_labelling(calib_dir: str | Path, out_dir: str | Path, sensor: SensorConfig,
                  labels_file: str | Path | None = None) -> tuple[list[PressLabel], Path]:
    """Label a calibration folder; writes ``out_dir/labels.csv`` and ``out_dir/overlays/``."""
    calib = load_calibration_set(calib_dir, sensor.shape)
    labels = labels_for(calib, sensor, labels_file)
    path = write_labels(Path(out_dir) / "labels.csv", labels)
    write_overlays(calib, labels, Path(out_dir) / "overlays", margin_px=rim_margin_px(sensor.mm_per_px))
    return labels, path


def run_training(
    calib_dir: str | Path,
    out_dir: str | Path,
    sensor: SensorConfig,
    cfg: TrainConfig,
    labels_file: str | Path | None = None,
    test_fraction: float = 0.2,
    reference: str | Path | None = None,
    colour_model: bool = False,
    say=print,
) -> dict[str, Any]:
    """Train a model on a calibration folder and write, under ``out_dir``:
    ``model.pt`` (with metadata), ``labels.csv``, ``overlays/``, ``training_curve.png``,
    ``training.json``, ``evaluation.json`` and ``evaluation.txt`` (held-out errors per
    press, beside ``reference`` when given) and, with ``colour_model``, ``colour_model.pt``.
    Returns the evaluation summary."""
    cfg.validate()  # before the labelling
    out = Path(out_dir)
    calib = load_calibration_set(calib_dir, sensor.shape)
    labels = labels_for(calib, sensor, labels_file)
    write_labels(out / "labels.csv", labels)
    write_overlays(calib, labels, out / "overlays", margin_px=rim_margin_px(sensor.mm_per_px))
    by_dir = {lb.reldir: lb for lb in labels}
    flagged = [lb for lb in labels if not lb.reliable]
    say(f"{len(labels)} presses labelled, {len(flagged)} flagged" + "".join(
        f"\n  warning: skipping {lb.reldir}: {lb.reason}" for lb in flagged))
    data = build_dataset(calib, by_dir, sensor.mm_per_px, cfg.seed, test_fraction)
    used = len(data.train.reldirs) + len(data.test.reldirs)
    if used < ADVISABLE_PRESSES:
        say(f"warning: only {used} usable presses ({len(data.train.reldirs)} to train on, {len(data.test.reldirs)} "
            f"held out); about {ADVISABLE_PRESSES} spread over the gel are advisable (docs/calibration.md)")
    if not data.test.reldirs:
        say("warning: no press is held out for testing: evaluation.json stays empty and the model's accuracy is "
            "unmeasured; record more presses or raise --test-fraction")
    say(f"{len(data.train)} train / {len(data.test)} test samples; training MLP 5-"
        f"{'-'.join(map(str, cfg.hidden))}-2 on {cfg.device}")
    result = train_model(data.train, cfg, data.test if len(data.test) else None)
    model = result.model
    say(f"trained in {result.seconds:.1f} s")
    if cfg.restarts > 1:
        fits = ", ".join(f"seed {r['seed']} {r['train_mae']:.4f}" for r in result.restarts)
        say(f"kept seed {result.seed}; training angle MAE (rad): {fits}")
    evals = {"model": evaluate_model(model, calib, by_dir, data.split["test"], sensor.mm_per_px)} \
        if data.test.reldirs else {}
    if reference is not None and evals:
        ref_model, _ = load_model(reference, cfg.device)
        evals["reference"] = evaluate_model(ref_model, calib, by_dir, data.split["test"], sensor.mm_per_px)
    summary = {name: e.to_dict() for name, e in evals.items()}
    if reference is not None:
        summary["reference_path"] = str(reference)
    metrics = {f"heldout_{k}": v for k, v in (summary.get("model") or {}).items()
               if k in ("angle_mae_rad", "normal_mae_deg", "n_presses", "n_px", "background_mean_abs_angle_rad")}
    if "reference" in summary:
        metrics["reference_heldout_angle_mae_rad"] = summary["reference"]["angle_mae_rad"]
        metrics["reference_heldout_normal_mae_deg"] = summary["reference"]["normal_mae_deg"]
    meta = {
        "sensor": sensor.name,
        "mm_per_px": sensor.mm_per_px,
        "image_size": list(calib.shape),
        "data_fingerprint": calib.fingerprint(),
        "seed": cfg.seed,
        "model_seed": result.seed,
        "restarts": result.restarts,
        "split": data.split,
        "skipped": data.skipped,
        "train_config": {k: list(v) if isinstance(v, tuple) else v for k, v in asdict(cfg).items()},
        "train_seconds": result.seconds,
        "labels": [[lb.reldir, lb.cx, lb.cy, lb.radius, lb.reliable] for lb in labels],
        "metrics": metrics,
        "torch": str(torch.__version__),
    }
    save_model(out / "model.pt", model.cpu(), meta)
    write_training_report(out, result, cfg, {"metrics": metrics})
    (out / "evaluation.json").write_text(json.dumps(summary, indent=2))
    if evals:
        table = format_comparison(evals) + "\n\n" + format_slope_gain(evals)
        (out / "evaluation.txt").write_text(table + "\n")
        say(table)
    if colour_model:
        samples = colour_samples(calib, by_dir, [p.reldir for p in calib.presses], sensor.mm_per_px)
        cm, err = fit_colour_model(samples, seed=cfg.seed, device=cfg.device)
        cm.meta = {"sensor": sensor.name, "mm_per_px": sensor.mm_per_px, "image_size": list(calib.shape),
                   "data_fingerprint": calib.fingerprint(), "seed": cfg.seed, "train_mae_bgr": err}
        cm.to("cpu").save(out / "colour_model.pt")
        say(f"colour model: mean |BGR error| {err:.2f} on its training pixels")
    return {"metrics": metrics, "evaluation": summary, "out_dir": str(out),
            "angle_mae_rad": metrics.get("heldout_angle_mae_rad", math.nan)}
