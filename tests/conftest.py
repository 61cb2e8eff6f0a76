"""Shared fixtures: devices and dtypes to parametrise over, the shared data folder, and
torch's thread count restored after every test."""

from __future__ import annotations

import pytest
import torch

from tactile_slam.config import gelsight_mini_data

DEVICES = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])


@pytest.fixture(params=DEVICES)
def device(request) -> torch.device:
    return torch.device(request.param)


@pytest.fixture(params=[torch.float32, torch.float64], ids=["f32", "f64"])
def dtype(request) -> torch.dtype:
    return request.param


@pytest.fixture(scope="session")
def mini_data():
    """The real GelSight Mini data folder (:func:`~tactile_slam.config.gelsight_mini_data`;
    skips when absent)."""
    path = gelsight_mini_data()
    if not path.is_dir():
        pytest.skip(f"{path} is not present")
    return path


@pytest.fixture(autouse=True)
def restore_torch_threads():
    """Benchmarks and CLIs set torch's thread count for the process (``--threads``); put it
    back after each test, so that no test runs under the count an earlier one left
    (results that depend on summation order would then depend on the test order)."""
    before = torch.get_num_threads()
    yield
    torch.set_num_threads(before)


@pytest.fixture
def one_thread():
    """One torch thread for the test (put back afterwards by :func:`restore_torch_threads`)."""
    torch.set_num_threads(1)
