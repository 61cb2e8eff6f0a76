import json
import math

import numpy as np
import pytest
import torch

from tactile_slam.calibration.catalog import CalibrationDataError, load_calibration_set
from tactile_slam.calibration.evaluate import (
    SLOPE_EDGES, evaluate_model, format_comparison, format_slope_gain, slope_bins,
)
from tactile_slam.calibration.labels import PressLabel, label_presses
from tactile_slam.calibration.model import GradientMLP

from .conftest import MM_PER_PX


def _zero_model():
    m = GradientMLP()
    with torch.no_grad():
        for p in m.parameters():
            p.zero_()
    return m.eval()


def test_zero_model_matches_independent_computation(synthetic_calib):
    """A model predicting 0 everywhere: its angle MAE is the mean |target angle| and its
    normal error the mean tilt of the analytic normal, computed here in numpy."""
    calib = load_calibration_set(synthetic_calib)
    labels = {lb.reldir: lb for lb in label_presses(calib, MM_PER_PX, 2.0)}
    reldirs = ["6.310mm/0", "9.500mm/1"]
    ev = evaluate_model(_zero_model(), calib, labels, reldirs, MM_PER_PX)
    abs_sum, tilt_sum, n = 0.0, 0.0, 0
    for r in reldirs:
        lb, ball_r = labels[r], calib.press(r).ball_radius_px(MM_PER_PX)
        ys, xs = np.mgrid[0:240, 0:320]
        m = (xs - lb.cx) ** 2 + (ys - lb.cy) ** 2 < (lb.radius - 4) ** 2
        dx, dy = xs[m] - lb.cx, ys[m] - lb.cy
        dz = np.sqrt(ball_r**2 - dx**2 - dy**2)
        abs_sum += (np.abs(np.arctan2(dx, dz)) + np.abs(np.arctan2(dy, dz))).sum() / 2
        tilt_sum += np.arctan(np.hypot(dx / dz, dy / dz)).sum()
        n += m.sum()
    assert ev.angle_mae == pytest.approx(abs_sum / n, rel=1e-4)
    assert ev.normal_mae == pytest.approx(tilt_sum / n, rel=1e-4)
    assert ev.background_angle == 0.0
    assert [p.reldir for p in ev.per_press] == reldirs
    d = ev.to_dict()
    assert d["normal_mae_deg"] == pytest.approx(math.degrees(ev.normal_mae))
    assert d["n_px"] == n


def test_skips_unreliable(synthetic_calib):
    calib = load_calibration_set(synthetic_calib)
    labels = {lb.reldir: lb for lb in label_presses(calib, MM_PER_PX, 2.0)}
    labels["6.310mm/0"] = PressLabel("6.310mm/0", 1, 1, 20, reliable=False, reason="bad")
    ev = evaluate_model(_zero_model(), calib, labels, ["6.310mm/0", "6.310mm/1"], MM_PER_PX)
    assert [p.reldir for p in ev.per_press] == ["6.310mm/1"] and "bad" in ev.skipped["6.310mm/0"]
    with pytest.raises(CalibrationDataError, match="no press could be scored"):
        evaluate_model(_zero_model(), calib, labels, ["6.310mm/0"], MM_PER_PX)
    with pytest.raises(CalibrationDataError, match="no label"):
        evaluate_model(_zero_model(), calib, {}, ["6.310mm/0"], MM_PER_PX)


def test_device(synthetic_calib, device):
    calib = load_calibration_set(synthetic_calib)
    labels = {lb.reldir: lb for lb in label_presses(calib, MM_PER_PX, 2.0)}
    cpu = evaluate_model(_zero_model(), calib, labels, ["6.310mm/2"], MM_PER_PX)
    dev = evaluate_model(_zero_model().to(device), calib, labels, ["6.310mm/2"], MM_PER_PX)
    assert dev.angle_mae == pytest.approx(cpu.angle_mae, rel=1e-5)


def test_reference_model_on_real_presses(mini_calib, mini_labels, reference_model):
    """The SDK model's gradients match the analytic ball on the real presses (method.md's
    yardstick is 0.099 rad with area-based labels; rim labels are tighter)."""
    reldirs = [r for r, lb in mini_labels.items() if lb.reliable][::5]
    ev = evaluate_model(reference_model, mini_calib, mini_labels, reldirs, MM_PER_PX)
    assert ev.angle_mae < 0.06
    assert math.degrees(ev.normal_mae) < 6.0
    assert ev.background_angle < 0.05
    table = format_comparison({"ref": ev, "zero": evaluate_model(_zero_model(), mini_calib, mini_labels, reldirs,
                                                                 MM_PER_PX)})
    assert table.count("\n") == len(reldirs) + 2 and "ALL" in table


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_slope_bins_gain_and_counts(dtype):
    """Decoded = 0.8 x true + a perpendicular part: the gain is 0.8 in every bin, the
    counts are numpy's histogram of |true|, and an empty bin reports NaN."""
    gen = torch.Generator().manual_seed(0)
    true = (torch.rand(5000, 2, generator=gen, dtype=torch.float64) - 0.5) * 1.2  # |g| < 0.85
    perp = torch.stack([-true[:, 1], true[:, 0]], 1) * 0.3
    err = torch.rand(5000, generator=gen, dtype=torch.float64)
    edges = (0.0, 0.2, 0.5, 1.0, 2.0)
    bins = slope_bins((0.8 * true + perp).to(dtype), true.to(dtype), err.to(dtype), edges)
    mag = true.norm(dim=1).numpy()
    counts, _ = np.histogram(mag, bins=edges)
    assert [b.n_px for b in bins] == counts.tolist() and counts[-1] == 0
    for b in bins[:-1]:
        assert b.gain == pytest.approx(0.8, abs=1e-5)
        sel = (mag >= b.lo) & (mag < b.hi)
        assert b.normal_mae == pytest.approx(float(err.numpy()[sel].mean()), rel=1e-5)
    assert math.isnan(bins[-1].gain) and math.isnan(bins[-1].normal_mae)


def test_zero_model_gain_is_zero_in_every_bin(synthetic_calib):
    """The zero model decodes G = 0: gain 0 wherever there are pixels; the bins hold every
    scored pixel; the text table has one row per bin and the JSON has no NaN or inf."""
    calib = load_calibration_set(synthetic_calib)
    labels = {lb.reldir: lb for lb in label_presses(calib, MM_PER_PX, 2.0)}
    ev = evaluate_model(_zero_model(), calib, labels, ["6.310mm/0", "9.500mm/1"], MM_PER_PX)
    assert sum(b.n_px for b in ev.by_slope) == sum(p.n_px for p in ev.per_press)
    assert all(b.gain == 0.0 for b in ev.by_slope if b.n_px)
    table = format_slope_gain({"zero": ev, "again": ev})
    assert table.count("\n") == len(SLOPE_EDGES) and "0.6-inf" in table
    json.dumps(ev.to_dict(), allow_nan=False)
