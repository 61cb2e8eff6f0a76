"""The shipped GelSight Mini model: loadable, documented, and at least as accurate as the
SDK's reference model on the presses it held out."""

from pathlib import Path

import pytest

from tactile_slam.calibration.evaluate import evaluate_model
from tactile_slam.calibration.model import load_model
from tactile_slam.config import gelsight_mini

from .conftest import MM_PER_PX

SHIPPED = Path(__file__).resolve().parents[2] / "models" / "gelsight_mini.pt"
pytestmark = pytest.mark.skipif(not SHIPPED.exists(), reason="models/gelsight_mini.pt not built")


def test_metadata():
    model, meta = load_model(SHIPPED)
    assert model.hidden == (32, 32, 32)
    assert meta["sensor"] == "GelSight Mini" and meta["mm_per_px"] == MM_PER_PX and meta["image_size"] == [240, 320]
    assert len(meta["split"]["test"]) >= 10 and not set(meta["split"]["test"]) & set(meta["split"]["train"])
    assert {"heldout_angle_mae_rad", "reference_heldout_angle_mae_rad"} <= set(meta["metrics"])
    assert gelsight_mini().sensor.resolved_model_path() == SHIPPED


def test_no_worse_than_reference_on_heldout(mini_calib, mini_labels, reference_model):
    model, meta = load_model(SHIPPED)
    assert meta["data_fingerprint"] == mini_calib.fingerprint()
    heldout = meta["split"]["test"]
    ours = evaluate_model(model, mini_calib, mini_labels, heldout, MM_PER_PX)
    ref = evaluate_model(reference_model, mini_calib, mini_labels, heldout, MM_PER_PX)
    assert ours.angle_mae <= ref.angle_mae
    assert ours.angle_mae == pytest.approx(meta["metrics"]["heldout_angle_mae_rad"], rel=1e-3)
