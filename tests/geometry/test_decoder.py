import pytest
import torch

from tactile_slam.calibration.model import (
    CalibrationModelError,
    GradientDecoder,
    GradientMLP,
    load_model,
    model_sensor_mismatch,
    mlp_rows,
    pixel_features,
    save_model,
)
from tactile_slam.config import ContactConfig, SensorConfig


def test_reference_model_loads(mini_data):
    model, meta = load_model(mini_data / "reference_model" / "nnmodel.pth")
    assert model.hidden == (32, 32, 32) and meta == {}
    assert sum(p.numel() for p in model.parameters()) == 2370
    assert not model.training


def test_roundtrip(tmp_path):
    torch.manual_seed(0)
    m = GradientMLP((16, 8))
    save_model(tmp_path / "m.pt", m, {"sensor": "test"})
    back, meta = load_model(tmp_path / "m.pt")
    assert back.hidden == (16, 8) and meta == {"sensor": "test"}
    x = torch.rand(10, 5)
    torch.testing.assert_close(back(x), m(x))


def test_bad_files(tmp_path):
    with pytest.raises(CalibrationModelError, match="not found"):
        load_model(tmp_path / "none.pt")
    (tmp_path / "junk.pt").write_bytes(b"not a zip")
    with pytest.raises(CalibrationModelError, match="cannot read"):
        load_model(tmp_path / "junk.pt")
    torch.save({"fc1.weight": torch.zeros(3, 4)}, tmp_path / "bad.pt")
    with pytest.raises(CalibrationModelError):
        load_model(tmp_path / "bad.pt")


def test_features_layout():
    img = torch.zeros(1, 2, 4, 3, dtype=torch.uint8)
    img[0, 1, 3] = torch.tensor([255, 0, 51], dtype=torch.uint8)
    f = pixel_features(img)
    torch.testing.assert_close(f[0, 1, 3], torch.tensor([1.0, 0.0, 0.2, 0.75, 0.5]))


def test_decoder_background_gives_zero_and_skip_is_consistent(device):
    torch.manual_seed(0)
    m = GradientMLP().to(device)
    bg = torch.rand(24, 32, 3, device=device) * 255
    dec = GradientDecoder(m, bg, skip_color_dist=0)
    g = dec(bg[None].repeat(2, 1, 1, 1))
    assert g.shape == (2, 24, 32, 2)
    torch.testing.assert_close(g, torch.zeros_like(g), atol=1e-5, rtol=0)
    img = bg.clone()
    img[5:10, 5:10] += 40
    full = GradientDecoder(m, bg, skip_color_dist=0)(img[None])
    sparse = GradientDecoder(m, bg, skip_color_dist=8)(img[None])
    torch.testing.assert_close(sparse[0, 5:10, 5:10], full[0, 5:10, 5:10])
    assert (sparse[0, :2] == 0).all()


def test_decoder_takes_numpy_like_the_frame_builder():
    """Backgrounds and images as OpenCV and the sources give them (numpy arrays) decode as
    tensors do; the default skip is the pipelines' ``contact.mlp_skip_color_dist``."""
    torch.manual_seed(0)
    m = GradientMLP()
    bg = torch.rand(24, 32, 3) * 255
    img = bg.clone()
    img[5:10, 5:10] += 40
    ref = GradientDecoder(m, bg)(img[None])
    torch.testing.assert_close(GradientDecoder(m, bg.numpy())(img[None].numpy()), ref, rtol=0, atol=0)
    assert GradientDecoder(m, bg).skip_color_dist == ContactConfig().mlp_skip_color_dist
    with pytest.raises(ValueError, match="background must be a torch tensor or a numpy array"):
        GradientDecoder(m, bg.tolist())


def test_decoder_bad_shape():
    dec = GradientDecoder(GradientMLP(), torch.zeros(24, 32, 3))
    with pytest.raises(ValueError, match="image batch"):
        dec(torch.zeros(1, 24, 31, 3))


@pytest.mark.parametrize("skip", [0.0, 8.0])
def test_decoder_chunks_give_identical_gradients(skip):
    """The model runs ``chunk_pixels`` rows at a time on the CPU: chunks smaller than the
    changed pixels, not dividing them, or one chunk for all give the same gradients (to
    rounding: a one-row product may take another kernel), and a frame with nothing
    changed decodes to zero."""
    torch.manual_seed(1)
    m = GradientMLP()
    bg = torch.rand(24, 32, 3) * 255
    img = bg[None].repeat(3, 1, 1, 1)
    img[0, 4:20, 3:30] += 60
    img[1] = torch.rand(24, 32, 3) * 255
    whole = GradientDecoder(m, bg, skip, chunk_pixels=0)(img)
    assert whole[0].abs().sum() > 0 and (whole[2] == 0).all()
    for chunk in (1, 7, 500, 24 * 32 * 3, 10 ** 6):
        torch.testing.assert_close(GradientDecoder(m, bg, skip, chunk_pixels=chunk)(img), whole, rtol=1e-6,
                                   atol=1e-6)
    assert (GradientDecoder(m, bg, skip, chunk_pixels=7)(bg[None]) == 0).all()


@pytest.mark.parametrize("chunk", [-1, 1.5, True, "8"])
def test_decoder_bad_chunk(chunk):
    with pytest.raises(ValueError, match="chunk_pixels"):
        GradientDecoder(GradientMLP(), torch.zeros(24, 32, 3), chunk_pixels=chunk)


@pytest.mark.parametrize("hidden", [(32, 32, 32), (16,), (8, 24)])
def test_mlp_rows_equals_the_module(hidden, dtype, device):
    """The chunked inference with reused buffers and in-place ReLU gives the module's
    forward (to rounding) for any chunk size, hidden widths that differ per layer, an
    empty input, and leaves the parameters without gradients."""
    torch.manual_seed(2)
    m = GradientMLP(hidden).to(device, dtype)
    x = torch.randn(1000, 5, dtype=dtype, device=device)
    want = m(x).detach()
    tol = 1e-12 if dtype == torch.float64 else 1e-5
    for rows in (0, 1, 7, 256, 1000, 4096):
        got = mlp_rows(m.layers, x, rows)
        assert got.shape == (1000, 2) and got.dtype == dtype and not got.requires_grad
        torch.testing.assert_close(got, want, rtol=tol, atol=tol)
    assert mlp_rows(m.layers, x[:0], 16).shape == (0, 2)


def test_mlp_rows_bad_input():
    """A negative or non-integer chunk, and rows of the wrong width or rank, are refused
    with the problem named (a negative chunk would otherwise return unfilled rows)."""
    m = GradientMLP()
    x = torch.randn(10, 5)
    for rows in (-1, 2.5, True):
        with pytest.raises(ValueError, match="chunk_pixels"):
            mlp_rows(m.layers, x, rows)
    for bad in (torch.randn(10, 4), torch.randn(10), torch.randn(2, 10, 5)):
        with pytest.raises(ValueError, match="mlp_rows"):
            mlp_rows(m.layers, bad, 4)


def test_model_of_another_field_of_view_is_named():
    """The same gel at another resolution is fine (positions are fractions of the image);
    another field of view, or a crop, is not; SDK files (no meta) are not checked."""
    mini = SensorConfig()
    assert model_sensor_mismatch({"image_size": [240, 320], "mm_per_px": 0.0634}, mini) is None
    assert model_sensor_mismatch({"image_size": [480, 640], "mm_per_px": 0.0317}, mini) is None
    assert model_sensor_mismatch({}, mini) is None
    why = model_sensor_mismatch({"image_size": [240, 320], "mm_per_px": 0.05}, mini)
    assert why is not None and "16.00 x 12.00 mm field of view" in why and "20.29 x 15.22" in why
    assert model_sensor_mismatch({"image_size": [215, 290], "mm_per_px": 0.0634}, mini) is not None
