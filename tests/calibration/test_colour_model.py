from pathlib import Path

import pytest
import torch

from tactile_slam.calibration.catalog import CalibrationDataError, load_calibration_set
from tactile_slam.calibration.colour_model import ColourModel, colour_samples, fit_colour_model
from tactile_slam.calibration.labels import label_presses

from .conftest import COLOUR_GAIN, COLOUR_GAIN_Y, MM_PER_PX, synthetic_slopes

SHIPPED = Path(__file__).resolve().parents[2] / "models" / "gelsight_mini_colour.pt"


def test_shapes_and_device(device, dtype):
    model = ColourModel((8,)).to(device)
    out = model(torch.zeros(2, 6, 7, 2, dtype=dtype, device=device))
    assert out.shape == (2, 6, 7, 3) and out.dtype == torch.float32 and out.device.type == device.type


def test_chunks_give_the_same_colours():
    """The MLP runs ``chunk_pixels`` rows at a time on the CPU: any chunk size, dividing
    the pixels or not, gives the colours of one pass (to rounding)."""
    torch.manual_seed(2)
    model = ColourModel((16, 16))
    g = torch.randn(3, 10, 13, 2) * 0.3
    whole = ColourModel((16, 16), chunk_pixels=0)
    whole.net.load_state_dict(model.net.state_dict())
    ref = whole(g)
    assert ref.abs().sum() > 0
    with torch.no_grad():  # the module's own forward, independent of the chunked inference
        direct = model.net(ColourModel.features(g).reshape(-1, 4)).reshape(3, 10, 13, 3)
    torch.testing.assert_close(ref, direct, rtol=1e-6, atol=1e-6)
    assert (model(torch.zeros(1, 10, 13, 2)) == 0).all()
    for chunk in (1, 37, 390, 10 ** 6):
        model.chunk_pixels = chunk
        torch.testing.assert_close(model(g), ref, rtol=1e-6, atol=1e-6)
    for bad in (-1, 2.5, False):
        with pytest.raises(ValueError, match="chunk_pixels"):
            ColourModel((8,), chunk_pixels=bad)


def test_bad_input():
    model = ColourModel((8,))
    with pytest.raises(ValueError, match=r"\(B, H, W, 2\)"):
        model(torch.zeros(6, 7, 2))
    with pytest.raises(ValueError, match="NaN"):
        model(torch.full((1, 2, 2, 2), float("nan")))


def test_save_load(tmp_path):
    torch.manual_seed(0)
    model = ColourModel((8, 8), meta={"sensor": "x"})
    model.save(tmp_path / "c.pt")
    back = ColourModel.load(tmp_path / "c.pt")
    g = torch.randn(1, 5, 5, 2)
    assert torch.equal(back(g), model(g)) and back.meta == {"sensor": "x"} and back.hidden == (8, 8)
    with pytest.raises(CalibrationDataError, match="not found"):
        ColourModel.load(tmp_path / "missing.pt")
    torch.save({"format": "other"}, tmp_path / "o.pt")
    with pytest.raises(CalibrationDataError, match="not a tactile-slam colour model"):
        ColourModel.load(tmp_path / "o.pt")


def test_fit_recovers_synthetic_sensor(synthetic_calib):
    """The synthetic sensor's colour is linear in the slopes: a fitted model reproduces it
    on a press it never saw, and gives 0 for a flat gel."""
    calib = load_calibration_set(synthetic_calib)
    labels = {lb.reldir: lb for lb in label_presses(calib, MM_PER_PX, 2.0)}
    samples = colour_samples(calib, labels, [p.reldir for p in calib.presses], MM_PER_PX)
    model, err = fit_colour_model(samples, hidden=(32, 32), epochs=30, batch_size=256)
    assert err < 3.0
    g = torch.from_numpy(synthetic_slopes(150.0, 100.0, 22.0, 49.76)).float()
    inside = g.norm(dim=-1) < 0.45  # within the range of slopes seen in training
    expected = g[..., :1] * torch.tensor(COLOUR_GAIN).float() + g[..., 1:] * torch.tensor(COLOUR_GAIN_Y).float()
    got = model(g[None])[0]
    assert (got - expected)[inside].abs().mean() < 3.0
    assert model(torch.zeros(1, 240, 320, 2)).abs().max() == 0  # flat gel: the background, exactly


def test_no_samples(synthetic_calib):
    calib = load_calibration_set(synthetic_calib)
    with pytest.raises(CalibrationDataError, match="no reliable"):
        colour_samples(calib, {}, ["6.310mm/0"], MM_PER_PX)


@pytest.mark.skipif(not SHIPPED.exists(), reason="shipped colour model not built")
def test_shipped_colour_model():
    model = ColourModel.load(SHIPPED)
    assert model.meta["sensor"] == "GelSight Mini" and model.meta["image_size"] == [240, 320]
    assert model(torch.zeros(1, 240, 320, 2)).abs().max() == 0
    assert model.meta["train_mae_bgr"] < 5.0
    g = torch.zeros(1, 240, 320, 2)
    g[..., 0] = 0.5
    assert model(g).abs().mean() > 5.0  # a tilt changes the colour visibly
