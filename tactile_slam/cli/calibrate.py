"""``tactile-slam calibrate label|train|evaluate|collect``: sensor calibration from ball presses.

See docs/calibration.md for the folder layout, the labels file and the workflow.
"""

from __future__ import annotations

import json
from pathlib import Path

import torch

from tactile_slam.calibration.catalog import load_calibration_set
from tactile_slam.calibration.evaluate import evaluate_model, format_comparison, format_slope_gain
from tactile_slam.calibration.model import load_model
from tactile_slam.calibration.train import LOSSES, TrainConfig
from tactile_slam.calibration.workflow import labels_for, run_labelling, run_training
from tactile_slam.cli.arguments import output_file, output_folder, positive_int, positive_int_list
from tactile_slam.cli.devices import add_device_argument
from tactile_slam.config import load_config


def _common(p, threads: bool = True) -> None:
    p.add_argument("--config", default=None, help="preset name (gelsight_mini, digit) or YAML path")
    if threads:
        p.add_argument("--threads", type=positive_int, default=1,
                       help="torch CPU threads (default 1: the small MLP gains nothing from more)")


def _label(args) -> int:
    torch.set_num_threads(args.threads)
    sensor = load_config(args.config).sensor
    out = Path(args.out or args.calib_dir)
    labels, path = run_labelling(args.calib_dir, out, sensor, args.labels)
    flagged = [lb for lb in labels if not lb.reliable]
    print(f"labelled {len(labels)} presses -> {path}; overlays in {out / 'overlays'} (overview.png)")
    for lb in flagged:
        print(f"  flagged {lb.reldir}: {lb.reason}")
    return 0


def _train(args) -> int:
    torch.set_num_threads(args.threads)
    sensor = load_config(args.config).sensor
    cfg = TrainConfig(
        hidden=args.hidden, epochs=args.epochs, batch_size=args.batch_size,
        lr=args.lr, lr_step=args.lr_step, loss=args.loss, seed=args.seed, device=args.device,
        restarts=args.restarts,
    )
    out = Path(args.out) if args.out else Path(args.calib_dir) / "model"
    summary = run_training(args.calib_dir, out, sensor, cfg, args.labels, args.test_fraction, args.reference,
                           args.colour_model)
    print(f"model and report in {out}")
    if args.json:
        Path(args.json).write_text(json.dumps(summary, indent=2))
    return 0


def _evaluate(args) -> int:
    torch.set_num_threads(args.threads)
    sensor = load_config(args.config).sensor
    device = args.device
    calib = load_calibration_set(args.calib_dir, sensor.shape)
    labels = {lb.reldir: lb for lb in labels_for(calib, sensor, args.labels)}
    model, meta = load_model(args.model, device)
    reldirs = [p.reldir for p in calib.presses]
    which = "all presses"
    if args.presses == "heldout" or (args.presses == "auto" and meta.get("data_fingerprint") == calib.fingerprint()):
        if meta.get("data_fingerprint") != calib.fingerprint() or "split" not in meta:
            raise ValueError(f"{args.model} was not trained on {args.calib_dir}: it has no held-out presses there")
        if not meta["split"]["test"]:
            raise ValueError(f"{args.model} was trained with no press held out: evaluate it with --presses all "
                             "(in-sample) or on another calibration folder")
        reldirs, which = list(meta["split"]["test"]), "the model's held-out presses"
    evals = {Path(args.model).name: evaluate_model(model, calib, labels, reldirs, sensor.mm_per_px)}
    if args.reference:
        ref, _ = load_model(args.reference, device)
        evals[f"reference:{Path(args.reference).name}"] = evaluate_model(ref, calib, labels, reldirs,
                                                                         sensor.mm_per_px)
    print(f"evaluated on {which} ({len(reldirs)})")
    for reldir, reason in next(iter(evals.values())).skipped.items():
        print(f"  warning: skipped {reldir}: {reason}")
    print(format_comparison(evals))
    print()
    print(format_slope_gain(evals))
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps({"presses": which, **{k: e.to_dict() for k, e in evals.items()}},
                                              indent=2))
    return 0


def _collect(args) -> int:
    from tactile_slam.calibration.collect import CollectPlan, collect_calibration
    from tactile_slam.io.camera import CameraSource

    sensor = load_config(args.config).sensor
    device = int(args.camera) if args.camera.isdigit() else (args.camera or sensor.name)
    source = CameraSource(device, sensor.shape, sensor.fps, (sensor.raw_height, sensor.raw_width))
    try:
        plan = CollectPlan(tuple(float(d) for d in args.diameters.split(",")), args.presses, sensor.shape,
                           sensor.mm_per_px, sensor.max_indentation_mm, sensor.background_frames)
        collect_calibration(args.out, lambda: source.read().bgr, plan, prompt=input, say=print)
    finally:
        source.close()
    return 0


def register(sub) -> None:
    p = sub.add_parser("calibrate", help="calibrate a sensor from ball presses (label, train, evaluate, collect)")
    csub = p.add_subparsers(dest="action", required=True)

    lp = csub.add_parser("label", help="detect the contact circle of every press; write labels.csv and overlays")
    lp.add_argument("calib_dir")
    lp.add_argument("--out", type=output_folder, help="output folder (default: the calibration folder)")
    lp.add_argument("--labels", help="labels CSV whose rows override detection")
    _common(lp)
    lp.set_defaults(func=_label)

    tp = csub.add_parser("train", help="label, train the MLP and report held-out errors")
    tp.add_argument("calib_dir")
    tp.add_argument("--out", type=output_folder, help="output folder (default: CALIB_DIR/model)")
    tp.add_argument("--labels", help="labels CSV whose rows override detection")
    tp.add_argument("--hidden", type=positive_int_list, default=(32, 32, 32),
                    help="hidden layer sizes, comma-separated")
    tp.add_argument("--epochs", type=int, default=TrainConfig.epochs)
    tp.add_argument("--batch-size", type=int, default=TrainConfig.batch_size)
    tp.add_argument("--lr", type=float, default=TrainConfig.lr)
    tp.add_argument("--lr-step", type=int, default=TrainConfig.lr_step, help="epochs per learning-rate halving")
    tp.add_argument("--loss", default=TrainConfig.loss, choices=sorted(LOSSES))
    tp.add_argument("--seed", type=int, default=0)
    tp.add_argument("--restarts", type=int, default=TrainConfig.restarts,
                    help="models trained from seeds seed, seed+1, ...; the best fit to the training presses is kept")
    tp.add_argument("--test-fraction", type=float, default=0.2)
    add_device_argument(tp)
    tp.add_argument("--reference", help="a reference model to evaluate beside the new one")
    tp.add_argument("--colour-model", action="store_true", help="also fit the simulator's colour model")
    tp.add_argument("--json", type=output_file, help="also write the summary to this JSON file")
    _common(tp)
    tp.set_defaults(func=_train)

    ep = csub.add_parser("evaluate", help="gradient- and normal-angle errors of a model against the analytic ball")
    ep.add_argument("calib_dir")
    ep.add_argument("--model", required=True, help="model file (tactile-slam .pt or SDK nnmodel.pth)")
    ep.add_argument("--labels", help="labels CSV (experiment_reldir,cx,cy,radius); detected when absent")
    ep.add_argument("--reference", help="a second model to evaluate side by side")
    ep.add_argument("--presses", choices=("auto", "all", "heldout"), default="auto",
                    help="auto: the model's held-out presses when it was trained on this folder, else all")
    add_device_argument(ep)
    ep.add_argument("--json", type=output_file, help="write the results to this JSON file")
    _common(ep)
    ep.set_defaults(func=_evaluate)

    cp = csub.add_parser("collect", help="guided capture of a calibration set from a live sensor")
    cp.add_argument("--out", required=True, type=output_folder, help="new calibration folder")
    cp.add_argument("--camera", default="",
                    help="camera index, or part of its V4L2 name (default: the sensor's name)")
    cp.add_argument("--diameters", default="6.31", help="ball diameters in mm, comma-separated")
    cp.add_argument("--presses", type=int, default=40, help="presses per ball")
    _common(cp, threads=False)
    cp.set_defaults(func=_collect)
