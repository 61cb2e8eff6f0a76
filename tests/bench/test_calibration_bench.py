"""`tactile-slam bench calibration` on the real presses, with a tiny training."""

import json
import math

from tactile_slam.calibration.catalog import load_calibration_set
from tactile_slam.cli.main import main


def test_diameter_split_holds_out_each_ball_size(tmp_path, mini_data):
    """``--split diameter``: one run per ball size, trained on the other size's presses and
    scored on that size's (the SDK model scored on the same presses beside it)."""
    out = tmp_path / "cal.json"
    assert main(["bench", "calibration", "--data", str(mini_data), "--out", str(out), "--split", "diameter",
                 "--hidden", "8", "--epochs", "2", "--restarts", "1", "--repeats", "1"]) == 0
    res = json.loads(out.read_text())["results"]
    assert res["settings"]["split"] == "diameter"
    runs = res["mlp_5-8-2"]["runs"]
    sizes = {}
    for p in load_calibration_set(mini_data / "calibration").presses:
        sizes[p.diameter_mm] = sizes.get(p.diameter_mm, 0) + 1
    assert [r["held_out_mm"] for r in runs] == sorted(sizes)
    for r in runs:
        assert r["test_presses"] == sizes[r["held_out_mm"]]
        assert r["train_presses"] == sum(sizes.values()) - r["test_presses"]
        for key in ("angle_mae_rad", "normal_mae_deg", "reference_angle_mae_rad", "reference_normal_mae_deg"):
            assert math.isfinite(r[key]) and r[key] > 0, key
