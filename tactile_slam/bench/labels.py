"""Press labelling: the contact-circle detector under other LED colours, its agreement with the SDK model, its time.

A different sensor has other LEDs, so the labels of a calibration folder should not
depend on the colours. Each *relit* set applies to every press and to the background
seeded per-channel gains, an offset and sensor noise (a third of it on the background,
which is usually a mean of frames), and every second set is mirrored left-right. Each
relit label is compared with the label of the same press as recorded:

* ``within_1_5px``: reliable and within 1.5 px (centre and radius);
* ``off_1_5_to_5px``: reliable, 1.5-5 px off (where the colour distance peaks moves a little);
* ``off_over_5px_reliable``: reliable but more than 5 px off: a wrong label that would be
  trained on (the number that matters);
* ``flagged``: not reliable (not trained on).

*Resampled* sets: the presses and background resized by ``--scales`` factors (640x480 and
160x120 by default) and labelled at the matching scale, with the detector's pixel
settings converted to it (``DetectionConfig.at_scale``) and, for comparison, as given
for 320x240; each label is compared with the recorded press's (centre offset and radius
difference in 320x240 pixels).

Agreement: the SDK's reference model (trained on hand labels) against the analytic ball
inside each reliable disc (gradient-angle MAE, rad): labels in the wrong place raise it.
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

import cv2
import numpy as np

from tactile_slam.bench.common import timing_stats, write_json
from tactile_slam.calibration.catalog import CalibrationSet, load_calibration_set
from tactile_slam.calibration.evaluate import evaluate_model
from tactile_slam.calibration.labels import DetectionConfig, PressLabel, detect_contact_circle
from tactile_slam.calibration.model import load_model
from tactile_slam.cli.arguments import positive_int
from tactile_slam.config import gelsight_mini_data, load_config


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--data", default=str(gelsight_mini_data()),
                   help="folder holding calibration/ and reference_model/nnmodel.pth")
    p.add_argument("--sets", type=positive_int, default=8, help="relit copies of the presses")
    p.add_argument("--gain", type=float, default=0.25, help="per-channel gains drawn from 1 +- this")
    p.add_argument("--offset", type=float, default=10.0, help="offsets drawn from +- this (grey levels)")
    p.add_argument("--noise", default="0.5,1.5", help="noise sigma range in grey levels, 'low,high'")
    p.add_argument("--seed", type=int, default=42)
    p.add_argument("--scales", default="2,0.5", help="resize factors of the resampled sets, comma-separated ('' none)")


def relight(image: np.ndarray, gains: np.ndarray, offset: float, noise: float, mirror: bool,
            rng: np.random.Generator) -> np.ndarray:
    """``(H, W, 3)`` BGR image with per-channel ``gains``, an ``offset``, Gaussian noise of
    ``noise`` grey levels, optionally mirrored left-right; float32 clipped to 0-255."""
    out = image.astype(np.float32)[:, ::-1] if mirror else image.astype(np.float32)
    out = out * gains.astype(np.float32) + offset + rng.normal(0.0, noise, out.shape).astype(np.float32)
    return np.clip(out, 0.0, 255.0)


def label_offset(label: PressLabel, ref: PressLabel, width: int, mirrored: bool) -> float:
    """Largest of the centre-coordinate and radius differences (px) between a relit label
    and the recorded press's label (a mirrored label is mapped back first)."""
    cx = (width - 1) - label.cx if mirrored else label.cx
    return max(abs(cx - ref.cx), abs(label.cy - ref.cy), abs(label.radius - ref.radius))


def resampled(calib: CalibrationSet, labels: dict[str, PressLabel], factor: float, mm_per_px: float,
              max_indentation_mm: float, cfg: DetectionConfig) -> dict:
    """The presses labelled reliable in ``labels``, resized by ``factor`` (cubic up, area
    down) and labelled at ``mm_per_px / factor`` with ``cfg``: how many stay reliable, why
    the others were flagged, and the centre offset and radius difference of the reliable
    ones from ``labels`` in the original pixels (pixel centres map as ``(x + 0.5) / f - 0.5``)."""
    h, w = calib.shape
    size = (round(w * factor), round(h * factor))
    interp = cv2.INTER_CUBIC if factor > 1 else cv2.INTER_AREA
    scale = mm_per_px / factor
    bg = cv2.resize(calib.background, size, interpolation=interp)
    centre, radius, flagged = [], [], {}
    for reldir, ref in labels.items():
        if not ref.reliable:
            continue
        press = calib.press(reldir)
        lb = detect_contact_circle(cv2.resize(calib.image(press), size, interpolation=interp), bg,
                                   press.ball_radius_px(scale), max_indentation_mm / scale, cfg, reldir)
        if not lb.reliable:
            flagged[reldir] = lb.reason
            continue
        cx, cy = (lb.cx + 0.5) / factor - 0.5, (lb.cy + 0.5) / factor - 0.5
        centre.append(float(np.hypot(cx - ref.cx, cy - ref.cy)))
        radius.append(lb.radius / factor - ref.radius)

    def spread(v: list[float]) -> dict:
        return {"median": float(np.median(v)), "p90": float(np.percentile(v, 90)), "max": float(np.max(v))} \
            if v else {}

    return {"image": list(size), "mm_per_px": scale, "reliable": len(centre), "flagged": flagged,
            "centre_offset_px": spread(centre), "radius_difference_px": spread(radius),
            "radius_difference_abs_px": spread([abs(r) for r in radius])}


def run(args) -> Path:
    low, high = (float(v) for v in args.noise.split(","))
    if args.sets < 1 or not 0 <= args.gain < 1 or args.offset < 0 or not 0 <= low <= high:
        raise ValueError(f"need --sets >= 1, 0 <= --gain < 1, --offset >= 0 and 0 <= noise low <= high; got "
                         f"{args.sets}, {args.gain}, {args.offset}, {args.noise}")
    factors = [float(v) for v in args.scales.split(",") if v.strip()]
    if not all(np.isfinite(f) and f > 0 for f in factors):
        raise ValueError(f"--scales must be resize factors > 0, got {args.scales!r}")
    sensor = load_config("gelsight_mini").sensor
    data_dir = Path(args.data)
    calib = load_calibration_set(data_dir / "calibration", sensor.shape)
    width = sensor.shape[1]
    max_ind = sensor.max_indentation_mm / sensor.mm_per_px

    def detect(image, background, press) -> PressLabel:
        return detect_contact_circle(image, background, press.ball_radius_px(sensor.mm_per_px), max_ind,
                                     reldir=press.reldir)

    labels, seconds = {}, []
    for press in calib.presses:
        t0 = time.perf_counter()
        labels[press.reldir] = detect(calib.image(press), calib.background, press)
        seconds.append(time.perf_counter() - t0)
    reliable = [r for r, lb in labels.items() if lb.reliable]
    ref_model, _ = load_model(data_dir / "reference_model" / "nnmodel.pth")
    agreement = evaluate_model(ref_model, calib, labels, reliable, sensor.mm_per_px)

    rng = np.random.default_rng(args.seed)
    sets, totals = [], dict.fromkeys(("within_1_5px", "off_1_5_to_5px", "off_over_5px_reliable", "flagged"), 0)
    for k in range(args.sets):
        gains = rng.uniform(1.0 - args.gain, 1.0 + args.gain, 3)
        offset, noise, mirror = float(rng.uniform(-args.offset, args.offset)), float(rng.uniform(low, high)), k % 2 == 1
        counts, wrong = dict.fromkeys(totals, 0), []
        for reldir in reliable:
            press = calib.press(reldir)
            lb = detect(relight(calib.image(press), gains, offset, noise, mirror, rng),
                        relight(calib.background, gains, offset, noise / 3.0, mirror, rng), press)
            off = label_offset(lb, labels[reldir], width, mirror)
            key = ("flagged" if not lb.reliable else "within_1_5px" if off <= 1.5
                   else "off_1_5_to_5px" if off <= 5.0 else "off_over_5px_reliable")
            counts[key] += 1
            if key == "off_over_5px_reliable":
                wrong.append({"press": reldir, "offset_px": off})
        for key in totals:
            totals[key] += counts[key]
        sets.append({"gains_bgr": gains.tolist(), "offset": offset, "noise": noise, "mirrored": mirror,
                     **counts, "wrong": wrong})
    scales = {}
    for factor in factors:
        scale = sensor.mm_per_px / factor
        scales[f"{factor:g}"] = {
            "converted": resampled(calib, labels, factor, sensor.mm_per_px, sensor.max_indentation_mm,
                                   DetectionConfig().at_scale(scale)),
            "unconverted": resampled(calib, labels, factor, sensor.mm_per_px, sensor.max_indentation_mm,
                                     DetectionConfig())}
    results = {
        "settings": {k: v for k, v in vars(args).items() if k != "func"},
        "presses": len(calib.presses), "reliable": len(reliable),
        "flagged": {r: lb.reason for r, lb in labels.items() if not lb.reliable},
        "label_time_per_press": timing_stats(seconds),
        "sdk_agreement": {"angle_mae_rad_pixel_weighted": agreement.angle_mae,
                          "angle_mae_rad_mean_per_press": statistics.mean(p.angle_mae for p in agreement.per_press),
                          "n_presses": len(agreement.per_press)},
        "relit": {"labels": len(reliable) * args.sets, **totals, "sets": sets},
        "resampled": scales,
        "labels": {r: {"cx": lb.cx, "cy": lb.cy, "radius": lb.radius, "reliable": lb.reliable}
                   for r, lb in labels.items()},
    }
    out = write_json(args.out, "labels", results)
    r = results["relit"]
    print(f"{results['reliable']} of {results['presses']} presses reliable; SDK model inside the discs "
          f"{agreement.angle_mae:.4f} rad; relit labels {r['labels']}: within 1.5 px {r['within_1_5px']}, "
          f"1.5-5 px {r['off_1_5_to_5px']}, wrong but reliable {r['off_over_5px_reliable']}, flagged {r['flagged']}")
    for factor, v in scales.items():
        c = v["converted"]
        print(f"resized x{factor} ({c['image'][0]}x{c['image'][1]}): reliable {c['reliable']} of {len(reliable)} "
              f"(pixel settings unconverted: {v['unconverted']['reliable']}); centre offset median "
              f"{c['centre_offset_px'].get('median', float('nan')):.2f} px, max "
              f"{c['centre_offset_px'].get('max', float('nan')):.2f} px")
    return out
