import pytest
import torch

from tactile_slam.calibration.model import CalibrationModelError, GradientMLP, load_model, save_model


def test_roundtrip(tmp_path, device):
    torch.manual_seed(0)
    model = GradientMLP((16, 24))
    meta = {"sensor": "GelSight Mini", "mm_per_px": 0.0634, "split": {"train": ["a"], "test": ["b"]}}
    save_model(tmp_path / "m.pt", model, meta)
    back, back_meta = load_model(tmp_path / "m.pt", device)
    assert back.hidden == (16, 24) and back_meta == meta and not back.training
    x = torch.rand(50, 5)
    tol = 0.0 if device.type == "cpu" else 1e-4  # GPU matmuls may use other kernels
    torch.testing.assert_close(back(x.to(device)).cpu(), model(x), rtol=tol, atol=tol)


def test_reference_model_loads(mini_data):
    model, meta = load_model(mini_data / "reference_model" / "nnmodel.pth")
    assert model.hidden == (32, 32, 32) and meta == {}
    assert sum(p.numel() for p in model.parameters()) == 2370


def test_sdk_layout_saved_by_us_loads_as_sdk(tmp_path):
    """A bare state dict (the SDK's format) of a model of ours loads back identically."""
    model = GradientMLP()
    torch.save(model.state_dict(), tmp_path / "nnmodel.pth")
    back, meta = load_model(tmp_path / "nnmodel.pth")
    assert meta == {} and torch.equal(back.fc4.weight, model.fc4.weight)


def test_corrupt_file(tmp_path):
    (tmp_path / "bad.pt").write_bytes(b"garbage")
    with pytest.raises(CalibrationModelError, match="cannot read"):
        load_model(tmp_path / "bad.pt")
