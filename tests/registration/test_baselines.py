from dataclasses import replace

import pytest
import torch

from tactile_slam.registration.baselines import BaselineConfig, contact_cloud, register_fpfh, register_icp
from tactile_slam.registration.result import RegistrationError, pose_error

from .surfaces import bumpy, frames, rigid, speckled

EYE = torch.eye(4, dtype=torch.float64)
TRUTH = [rigid(tx_mm=0.4, ty_mm=-0.2), rigid(rz_deg=3)]


@pytest.fixture(scope="module")
def scene():
    f = frames(replace(bumpy(1), depth=0.4e-3), [EYE] + TRUTH)  # a small contact keeps FPFH quick
    return f[0], f[1:]


def test_contact_cloud_matches_contact(scene):
    ref, _ = scene
    cloud = contact_cloud(ref)
    assert len(cloud.points) == int(ref.contact.sum()) and cloud.has_normals()
    with pytest.raises(RegistrationError, match="no contact"):
        contact_cloud(replace(ref, contact=torch.zeros_like(ref.contact)))


def test_icp_interface_and_accuracy(scene):
    ref, tars = scene
    res = register_icp(ref, tars)
    assert res.tar_T_ref.shape == (2, 4, 4) and res.tar_T_ref.dtype == torch.float64
    assert bool(torch.isnan(res.ccs).all()) and bool(torch.isnan(res.conditioning).all())
    assert (res.iterations == -1).all() and bool(res.ok.all())
    rot, trans = pose_error(res.tar_T_ref, torch.stack(TRUTH))
    assert (rot < 0.5).all() and (trans < 0.02).all(), (rot, trans)


def test_fpfh_ransac_icp_runs_from_init(scene):
    ref, tars = scene
    cfg = BaselineConfig(ransac_iters=500)  # same path, fewer RANSAC draws
    res = register_fpfh(ref, tars[:1], TRUTH[0], cfg)
    rot, trans = pose_error(res.tar_T_ref, TRUTH[0][None])
    assert float(rot) < 0.5 and float(trans) < 0.05, (rot, trans)


@pytest.mark.parametrize("init", [None, rigid(tx_mm=0.3)])
def test_fpfh_global_stage_recovers_a_turn_icp_cannot(init):
    """A 40-deg turn of a speckled surface: point-to-plane ICP from the start stays near
    it, the feature RANSAC finds the turn (from the identity, and composed with a
    start that already holds part of the motion)."""
    truth = rigid(rz_deg=40, tx_mm=0.3)
    f = frames(replace(speckled(0, amp=150e-6), depth=0.4e-3), [EYE, truth])
    cfg = BaselineConfig(ransac_iters=1000)
    icp_rot, _ = pose_error(register_icp(f[0], f[1:], init, cfg).tar_T_ref, truth[None])
    rot, trans = pose_error(register_fpfh(f[0], f[1:], init, cfg).tar_T_ref, truth[None])
    assert float(icp_rot) > 10.0, icp_rot
    assert float(rot) < 0.5 and float(trans) < 0.05, (rot, trans)


def test_bad_init(scene):
    ref, tars = scene
    with pytest.raises(RegistrationError, match="init_tar_T_ref"):
        register_icp(ref, tars, torch.full((4, 4), float("nan"), dtype=torch.float64))
    with pytest.raises(RegistrationError, match="cannot be paired"):
        register_icp(tars, tars[:1])
