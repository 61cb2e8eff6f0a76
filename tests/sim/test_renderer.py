"""Renderer conventions (method.md sections 1.2-1.4), exactness and errors."""

import numpy as np
import open3d as o3d
import pytest
import torch
from scipy.spatial.transform import Rotation

from tactile_slam.config import Config
from tactile_slam.geometry.curvature import normals_from_gradients
from tactile_slam.geometry.poisson import integrate_exact
from tactile_slam.sim.objects import make_object
from tactile_slam.sim.renderer import GelRenderer, RenderConfig, RenderError, central_gradients

S = Config().sensor.m_per_px
R_BALL = 0.010


@pytest.fixture(scope="module")
def ball():
    return make_object("ball", resolution_mm=0.15)


@pytest.fixture(scope="module")
def slab():
    """A flat block occupying z in [0, 10] mm (object frame), its top face at z = 0."""
    box = o3d.geometry.TriangleMesh.create_box(0.06, 0.06, 0.01).translate([-0.03, -0.03, 0.0])
    box.compute_vertex_normals()
    return box


def press_ball(depth_m, x=0.0, y=0.0, rot=np.eye(3)):
    """Sensor looking along +z at a ball centred on the origin, contact under (x, y)."""
    t = np.eye(4)
    t[:3, :3] = rot
    t[:3, 3] = [x, y, -R_BALL + depth_m]
    return t


def test_press_depth_and_position(ball, device):
    r = GelRenderer(ball, device=device)
    out = r.render(press_ball(0.001))
    h = out.height[0].cpu()
    assert out.height.device.type == device.type
    # deepest point under the image centre (between pixels 119/120 and 159/160), ~1 mm deep
    idx = torch.nonzero(h <= h.min() + 1e-3)
    assert torch.allclose(idx.float().mean(0), torch.tensor([119.5, 159.5]), atol=0.6)
    assert abs(h.min().item() * S - (-0.001)) < 0.03e-3
    assert out.in_contact.tolist() == [True]
    # without smoothing: contact where deeper than 0.03 mm, the cap of height
    # k = d - 0.03 mm, radius sqrt(2 R k - k^2) = 4.30 mm; the 5x5 square erosion takes
    # its mean half-width 2 px * 4/pi off the radius
    sharp = GelRenderer(ball, render_config=RenderConfig(elastomer_sigma_mm=0.0), device=device)
    area_mm2 = sharp.render(press_ball(0.001)).contact[0].sum().item() * (S * 1e3) ** 2
    k = 0.001 - 0.03e-3
    r_c = (np.sqrt(2 * R_BALL * k - k**2) - 2 * S * 4 / np.pi) * 1e3
    assert abs(area_mm2 - np.pi * r_c**2) / (np.pi * r_c**2) < 0.01


@pytest.mark.parametrize("axis", [0, 1])
def test_sensor_translation_moves_pattern_opposite(ball, axis):
    """Moving the sensor +10 px along its x (y) axis moves the pattern -10 px along columns
    (rows): the object moves the other way in the sensor frame. Hence NormalFlow's
    tar_T_ref for this pair is a translation of -10 px * s (method.md section 1.4)."""
    r = GelRenderer(ball, render_config=RenderConfig(elastomer_sigma_mm=0.0))
    a = press_ball(0.0008, x=0.002, y=-0.001)
    b = a.copy()
    b[:3, 3] += 10 * S * a[:3, axis]
    ha, hb = r.render(np.stack([a, b])).height.numpy()
    if axis == 0:
        assert np.allclose(hb[:, :-10], ha[:, 10:], atol=1e-3)
    else:
        assert np.allclose(hb[:-10], ha[10:], atol=1e-3)
    assert not np.allclose(ha, hb, atol=1e-3)


def _centroid_m(height):
    """Depth-weighted centroid of the indentation, sensor-frame metres (x, y)."""
    h, w = height.shape
    wgt = np.clip(-height, 0, None)
    r, c = np.meshgrid(np.arange(h), np.arange(w), indexing="ij")
    return np.array([((c - (w - 1) / 2) * wgt).sum(), ((r - (h - 1) / 2) * wgt).sum()]) / wgt.sum() * S


def test_sensor_rotation_about_z_rotates_pattern_back(ball):
    """Rotating the sensor by +theta about its z axis rotates the pattern by -theta."""
    r = GelRenderer(ball)
    a = press_ball(0.0008, x=0.003, y=0.001)
    theta = np.deg2rad(25)
    b = a.copy()
    b[:3, :3] = a[:3, :3] @ Rotation.from_euler("z", theta).as_matrix()
    ha, hb = r.render(np.stack([a, b])).height.numpy()
    ca, cb = _centroid_m(ha), _centroid_m(hb)
    rot = Rotation.from_euler("z", -theta).as_matrix()[:2, :2]
    # the contact centre is where the ball is nearest: (-3, -1) mm in sensor a
    assert np.allclose(ca, [-0.003, -0.001], atol=2e-5)
    assert np.allclose(cb, rot @ ca, atol=2e-5)


def test_tilted_plane_gradient_sign_and_normals(slab):
    """Sensor rolled by +alpha about its x axis over a flat face: the face rises toward
    +y, so gy = -tan(alpha), gx = 0, and the gel normal is minus the object's outward
    normal expressed in the sensor frame."""
    alpha = np.deg2rad(3.0)
    pose = np.eye(4)
    pose[:3, :3] = Rotation.from_euler("x", alpha).as_matrix()
    pose[:3, 3] = [0, 0, 0.001]
    out = GelRenderer(slab).render(pose)
    g = out.gradients[0, 20:-20, 20:-20].double()
    assert torch.allclose(g[..., 1], torch.full_like(g[..., 1], -np.tan(alpha)), atol=1e-4)
    assert torch.allclose(g[..., 0], torch.zeros_like(g[..., 0]), atol=1e-4)
    n_gel = normals_from_gradients(out.gradients)[0, 120, 160].double()
    outward_in_sensor = torch.as_tensor(pose[:3, :3].T @ np.array([0.0, 0.0, -1.0]))
    assert torch.allclose(-n_gel, outward_in_sensor, atol=1e-4)
    assert out.contact[0, 2:-2, 2:-2].all() and not out.contact[0, :2].any()  # border eroded


def test_ball_normals_match_surface(ball):
    """Gel normals from the rendered gradients are minus the sphere's outward normals."""
    depth = 0.0012
    out = GelRenderer(ball).render(press_ball(depth))
    n = normals_from_gradients(out.gradients)[0].double().numpy()
    h = out.height[0].double().numpy()
    rr, cc = np.meshgrid(np.arange(240), np.arange(320), indexing="ij")
    p = np.stack([(cc - 159.5) * S, (rr - 119.5) * S, h * S], -1)
    centre = np.array([0, 0, R_BALL - depth])
    outward = (p - centre) / np.linalg.norm(p - centre, axis=-1, keepdims=True)
    inner = np.hypot(p[..., 0], p[..., 1]) < 0.0035  # well inside the 4.9 mm contact disc
    cos = np.sum(-n[inner] * outward[inner], axis=1)
    assert np.degrees(np.arccos(np.clip(cos, -1, 1))).max() < 1.0


def test_gradients_integrate_back_to_height(ball):
    out = GelRenderer(ball).render(press_ball(0.001, x=0.001))
    h = out.height.double()
    hi = integrate_exact(out.gradients.double())
    diff = (hi - hi.mean()) - (h - h.mean())
    assert diff.abs().max() < 0.05  # px


def test_central_gradients_match_numpy(dtype):
    h = torch.randn(2, 6, 7, dtype=dtype)
    g = central_gradients(h)
    gy, gx = np.gradient(h.numpy(), axis=(1, 2))
    assert g.shape == (2, 6, 7, 2)
    assert np.allclose(g[..., 0].numpy(), gx) and np.allclose(g[..., 1].numpy(), gy)


def test_max_indentation_clamp(ball):
    out = GelRenderer(ball, render_config=RenderConfig(elastomer_sigma_mm=0.0)).render(press_ball(0.003))
    assert out.height.min().item() == pytest.approx(-2.0 / 0.0634, rel=1e-5)


def test_culling_is_exact_and_render_deterministic():
    mesh = make_object("knurled", resolution_mm=0.15)
    pose = np.eye(4)
    pose[:3, :3] = Rotation.from_euler("y", 90, degrees=True).as_matrix()  # look along +x at the side
    pose[:3, 3] = [-0.008 + 0.0007, 0.0, 0.001]
    culled = GelRenderer(mesh).render(np.stack([pose, pose]))
    full = GelRenderer(mesh, render_config=RenderConfig(cull_stride=1)).render(pose)
    assert culled.contact[0].sum() > 1000
    assert torch.equal(culled.height[:1], full.height)
    assert torch.equal(culled.height[0], culled.height[1])


def test_no_contact_away_from_object(ball):
    out = GelRenderer(ball).render(press_ball(-0.001))
    assert (out.height == 0).all() and not out.contact.any() and out.in_contact.tolist() == [False]


def test_cardinality(ball):
    r = GelRenderer(ball)
    poses = np.stack([press_ball(0.0005 + 0.0001 * k) for k in range(3)])
    out = r.render(poses)
    assert out.height.shape == (3, 240, 320) and out.gradients.shape == (3, 240, 320, 2)
    assert out.contact.shape == (3, 240, 320) and out.contact.dtype == torch.bool
    assert out.height.dtype == torch.float32
    assert r.surface_z(poses, r.pixel_xy[::8, ::8]).shape == (3, 30, 40)


def test_errors(ball):
    r = GelRenderer(ball)
    with pytest.raises(RenderError, match="NaN"):
        r.render(np.full((4, 4), np.nan))
    with pytest.raises(RenderError, match=r"\(N, 4, 4\)"):
        r.render(np.eye(3))
    bad = np.eye(4)
    bad[0, 0] = 2.0
    with pytest.raises(RenderError, match="rigid"):
        r.render(bad)
    with pytest.raises(RenderError, match="empty"):
        r.render(np.zeros((0, 4, 4)))
    with pytest.raises(RenderError, match="no triangles"):
        GelRenderer(o3d.geometry.TriangleMesh())
