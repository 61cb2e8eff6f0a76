"""A scan replayed through ``LoopedSource`` runs as the scan itself: the same
background (not the first frames it delivers, which are in contact) and the same video
indices (row 0 of the outputs is video frame 0, as for the scan)."""

from __future__ import annotations

import shutil

import numpy as np
import pytest
import torch

from tactile_slam.io import Scan
from tactile_slam.io.replay import LoopedSource
from tactile_slam.pipeline.online import OnlineOptions, OnlinePipeline
from tactile_slam.sim.episode import SimulationSettings, simulate_episode


@pytest.fixture(scope="module")
def scan(tmp_path_factory):
    """An image-level scan whose background is its 10-frame window (no background.png)."""
    ep = simulate_episode(tmp_path_factory.mktemp("ep_scan"),
                          SimulationSettings(object="seed", kind="scan", frames=150, level="image", seed=2))
    folder = tmp_path_factory.mktemp("scan")
    shutil.copy(ep / "gelsight.avi", folder / "gelsight.avi")
    return Scan(folder)


def test_a_looped_scan_runs_as_the_scan(scan, tmp_path):
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        opts = OnlineOptions(method="nf-kf", rate=None, progress=False, mesh=False)
        direct = OnlinePipeline(scan, scan.config, tmp_path / "scan", opts).run()
        looped = OnlinePipeline(LoopedSource(scan, len(scan)), scan.config, tmp_path / "looped", opts).run()
    finally:
        torch.set_num_threads(threads)
    assert scan.start == 10 and direct.stats["contact_frames"] > 0
    assert looped.stats["frames"] == direct.stats["frames"] == len(scan)
    np.testing.assert_array_equal(looped.frame_group, direct.frame_group)
    np.testing.assert_array_equal(looped.poses, direct.poses)  # NaN rows 0-9 alike
