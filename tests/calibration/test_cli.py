import json

import pytest

from tactile_slam.calibration.labels import read_labels
from tactile_slam.calibration.model import load_model
from tactile_slam.cli.main import main


def test_label_then_train_then_evaluate(synthetic_calib, tmp_path, capsys):
    out = tmp_path / "out"
    assert main(["calibrate", "label", str(synthetic_calib), "--out", str(out)]) == 0
    labels = read_labels(out / "labels.csv")
    assert len(labels) == 6 and (out / "overlays" / "overview.png").exists()
    assert main(["calibrate", "train", str(synthetic_calib), "--out", str(out / "m"), "--labels",
                 str(out / "labels.csv"), "--epochs", "2", "--hidden", "8,8", "--colour-model",
                 "--restarts", "2"]) == 0
    for name in ("model.pt", "training_curve.png", "training.json", "evaluation.json", "evaluation.txt",
                 "colour_model.pt"):
        assert (out / "m" / name).exists(), name
    model, meta = load_model(out / "m" / "model.pt")
    assert model.hidden == (8, 8)
    assert meta["sensor"] == "GelSight Mini" and meta["image_size"] == [240, 320] and meta["seed"] == 0
    assert len(meta["data_fingerprint"]) == 16 and set(meta["split"]) == {"train", "test"}
    assert "heldout_angle_mae_rad" in meta["metrics"]
    assert [r["seed"] for r in meta["restarts"]] == [0, 1] and meta["model_seed"] in (0, 1)
    assert meta["train_config"]["restarts"] == 2
    assert "true |g|" in (out / "m" / "evaluation.txt").read_text()  # the gain-by-slope table
    js = tmp_path / "ev.json"
    assert main(["calibrate", "evaluate", str(synthetic_calib), "--model", str(out / "m" / "model.pt"),
                 "--json", str(js)]) == 0
    doc = json.loads(js.read_text())
    assert doc["presses"] == "the model's held-out presses"
    assert main(["calibrate", "evaluate", str(synthetic_calib), "--model", str(out / "m" / "model.pt"),
                 "--presses", "all", "--json", str(js)]) == 0
    doc = json.loads(js.read_text())["model.pt"]
    assert doc["n_presses"] == 6 and sum(b["n_px"] for b in doc["by_slope"]) == doc["n_px"]


def test_evaluate_reference_on_real_data(mini_data, tmp_path):
    js = tmp_path / "ref.json"
    ref = mini_data / "reference_model" / "nnmodel.pth"
    rc = main(["calibrate", "evaluate", str(mini_data / "calibration"), "--model", str(ref), "--json", str(js)])
    assert rc == 0
    doc = json.loads(js.read_text())
    assert doc["presses"] == "all presses" and doc["nnmodel.pth"]["angle_mae_rad"] < 0.06


def test_bad_folder_is_a_clear_error(tmp_path, capsys):
    assert main(["calibrate", "label", str(tmp_path)]) == 2
    assert "catalog not found" in capsys.readouterr().err


def test_bad_restarts_fail_before_labelling(synthetic_calib, tmp_path, capsys):
    assert main(["calibrate", "train", str(synthetic_calib), "--out", str(tmp_path / "m"), "--restarts", "0"]) == 2
    assert "restarts must be a positive integer" in capsys.readouterr().err
    assert not (tmp_path / "m").exists()


def test_bad_schedule_fails_before_labelling(synthetic_calib, tmp_path, capsys):
    """``--lr-step 0`` ended in a ZeroDivisionError traceback after the labelling."""
    assert main(["calibrate", "train", str(synthetic_calib), "--out", str(tmp_path / "m"), "--lr-step", "0"]) == 2
    assert "lr_step must be >= 1" in capsys.readouterr().err
    assert not (tmp_path / "m").exists()


def test_bad_hidden_sizes_are_a_parse_error(synthetic_calib, tmp_path, capsys):
    for bad in ("abc", "32,,32", "0,32"):
        with pytest.raises(SystemExit):
            main(["calibrate", "train", str(synthetic_calib), "--out", str(tmp_path / "m"), "--hidden", bad])
        assert "argument --hidden: expected comma-separated integers >= 1" in capsys.readouterr().err


def test_heldout_needs_matching_data(synthetic_calib, mini_data, capsys):
    ref = mini_data / "reference_model" / "nnmodel.pth"
    assert main(["calibrate", "evaluate", str(synthetic_calib), "--model", str(ref), "--presses", "heldout"]) == 2
    assert "not trained on" in capsys.readouterr().err


def test_collect_with_a_fake_sensor(tmp_path, monkeypatch):
    """``calibrate collect`` through the io camera source: raw frames are cropped to the
    working image, the folder it writes labels cleanly."""
    import numpy as np

    import tactile_slam.io.camera as camera
    from tactile_slam.calibration.catalog import load_calibration_set
    from tactile_slam.calibration.labels import label_presses

    from .conftest import MM_PER_PX, press_image, render, synthetic_background

    bg = synthetic_background()
    working = [render(bg, np.zeros((240, 320, 2)), seed=i) for i in range(10)]
    working.append(press_image(150, 110, 25, 6.31, seed=11))

    class FakeCapture:
        def __init__(self):
            self.frames = list(working)

        def isOpened(self):
            return True

        def set(self, prop, value):
            return True

        def read(self):
            raw = np.zeros((336, 448, 3), np.uint8)  # crops to rows 48:288, cols 64:384
            raw[48:288, 64:384] = self.frames.pop(0)
            return True, raw

        def release(self):
            pass

    monkeypatch.setattr(camera, "open_cv_capture", lambda index: FakeCapture())
    monkeypatch.setattr("builtins.input", lambda message="": "")
    out = tmp_path / "new"
    assert main(["calibrate", "collect", "--out", str(out), "--camera", "0", "--presses", "1"]) == 0
    calib = load_calibration_set(out, (240, 320))
    (lb,) = label_presses(calib, MM_PER_PX, 2.0)
    assert abs(lb.cx - 150) < 1 and abs(lb.cy - 110) < 1 and abs(lb.radius - 25) < 1.5


def _train_tiny(calib, out, capsys) -> str:
    """``calibrate train`` of a 4-unit MLP for one epoch; what it printed."""
    assert main(["calibrate", "train", str(calib), "--out", str(out), "--epochs", "1", "--hidden", "4",
                 "--restarts", "1"]) == 0
    return capsys.readouterr().out


def test_train_skips_a_press_without_contact_and_warns_on_few_presses(synthetic_calib, tmp_path, capsys):
    """A press without contact stopped label, train and evaluate with NoContactError; now
    it is flagged and skipped, with a warning. Six presses are far fewer than advisable."""
    import cv2
    import numpy as np

    from .conftest import render, synthetic_background

    cv2.imwrite(str(synthetic_calib / "9.500mm/0/gelsight.png"),
                render(synthetic_background(), np.zeros((240, 320, 2)), seed=9))
    assert main(["calibrate", "label", str(synthetic_calib), "--out", str(tmp_path / "l")]) == 0
    assert "flagged 9.500mm/0: no contact" in capsys.readouterr().out
    out = tmp_path / "m"
    text = _train_tiny(synthetic_calib, out, capsys)
    assert "warning: skipping 9.500mm/0: no contact" in text
    assert "warning: only 5 usable presses (4 to train on, 1 held out); about 50" in text
    assert main(["calibrate", "evaluate", str(synthetic_calib), "--model", str(out / "model.pt"), "--presses",
                 "all"]) == 0
    assert "warning: skipped 9.500mm/0: unreliable label: no contact" in capsys.readouterr().out


def test_train_without_a_held_out_press_says_so(synthetic_calib, tmp_path, capsys):
    from .conftest import SYNTHETIC_PRESSES, write_calibration_folder

    calib = write_calibration_folder(tmp_path / "one", SYNTHETIC_PRESSES[:1])
    out = tmp_path / "m"
    text = _train_tiny(calib, out, capsys)
    assert "warning: only 1 usable presses" in text
    assert "warning: no press is held out for testing: evaluation.json stays empty" in text
    assert json.loads((out / "evaluation.json").read_text()) == {}
    assert main(["calibrate", "evaluate", str(calib), "--model", str(out / "model.pt")]) == 2
    assert "trained with no press held out: evaluate it with --presses all" in capsys.readouterr().err
