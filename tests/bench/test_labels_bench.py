"""bench labels: a two-set run on the real presses, the relighting helpers, argument checks."""

import argparse
import json

import numpy as np
import pytest

from tactile_slam.bench import labels
from tactile_slam.calibration.labels import PressLabel


def _args(tmp_path, data, *extra: str) -> argparse.Namespace:
    p = argparse.ArgumentParser()
    p.add_argument("--out", default=str(tmp_path / "labels.json"))
    labels.add_arguments(p)
    return p.parse_args(["--data", str(data), *extra])


def test_two_relit_sets_on_the_real_presses(tmp_path, mini_data):
    out = labels.run(_args(tmp_path, mini_data, "--sets", "2", "--scales", "2"))
    res = json.loads(out.read_text())["results"]
    assert res["presses"] == 59 and res["reliable"] >= 55
    relit = res["relit"]
    assert relit["labels"] == 2 * res["reliable"] == sum(
        relit[k] for k in ("within_1_5px", "off_1_5_to_5px", "off_over_5px_reliable", "flagged"))
    assert [s["mirrored"] for s in relit["sets"]] == [False, True]
    # the detector's point: no relit label lands in the wrong place while claiming to be reliable
    assert relit["off_over_5px_reliable"] == 0 and relit["within_1_5px"] >= 0.8 * relit["labels"]
    # the SDK model (hand labels) agrees with the analytic ball inside our discs
    assert res["sdk_agreement"]["angle_mae_rad_pixel_weighted"] < 0.045
    assert res["label_time_per_press"]["n"] == 59
    # at 640x480 with the pixel settings converted, every reliable press keeps its circle
    (factor, both), = res["resampled"].items()
    conv = both["converted"]
    assert factor == "2" and conv["image"] == [640, 480] and conv["mm_per_px"] == pytest.approx(0.0317)
    assert conv["reliable"] == res["reliable"] and not conv["flagged"]
    assert conv["centre_offset_px"]["max"] < 1.5 and conv["radius_difference_abs_px"]["max"] < 1.5
    assert both["unconverted"]["reliable"] + len(both["unconverted"]["flagged"]) == res["reliable"]


def test_relight_and_offset():
    rng = np.random.default_rng(0)
    img = np.full((4, 6, 3), 100, np.uint8)
    img[:, 0] = 0
    out = labels.relight(img, np.array([1.0, 2.0, 0.5]), 5.0, 0.0, True, rng)
    assert out.dtype == np.float32 and out.shape == img.shape
    assert (out[:, -1] == [5.0, 5.0, 5.0]).all()  # column 0 mirrored to the last column
    assert (out[:, 0] == [105.0, 205.0, 55.0]).all()
    assert labels.relight(img, np.array([3.0, 3.0, 3.0]), 0.0, 0.0, False, rng).max() == 255.0  # clipped
    ref = PressLabel("p", 10.0, 20.0, 25.0)
    assert labels.label_offset(PressLabel("p", 309.0, 21.0, 24.0), ref, 320, True) == pytest.approx(1.0)
    assert labels.label_offset(PressLabel("p", 12.0, 20.0, 30.0), ref, 320, False) == pytest.approx(5.0)


@pytest.mark.parametrize("bad", [["--gain", "1.0"], ["--offset", "-1"], ["--noise", "2,1"],
                                 ["--scales", "2,0"], ["--scales", "-1"], ["--scales", "nan"]])
def test_bad_settings_are_refused_before_any_work(tmp_path, bad):
    with pytest.raises(ValueError, match="--sets|--scales"):
        labels.run(_args(tmp_path, tmp_path / "missing", *bad))
    assert not (tmp_path / "labels.json").exists()


def test_no_relit_sets_is_a_parse_error(tmp_path, capsys):
    with pytest.raises(SystemExit):
        _args(tmp_path, tmp_path / "missing", "--sets", "0")
    assert "argument --sets: must be >= 1" in capsys.readouterr().err
