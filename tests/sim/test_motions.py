import numpy as np
import pytest

import open3d as o3d

from tactile_slam.sim.heldout import make_heldout
from tactile_slam.sim.motions import (MotionConfig, MotionError, lift, make_motion, tangent_basis, too_fast,
                                     transported_x)
from tactile_slam.sim.objects import make_object
from tactile_slam.sim.renderer import GelRenderer
from tactile_slam.sim.surface import SurfaceGuide


@pytest.fixture(scope="module")
def renderer():
    return GelRenderer(make_object("seed", resolution_mm=0.1))


def _is_rigid(p):
    r = p[:, :3, :3]
    return np.allclose(r @ r.transpose(0, 2, 1), np.eye(3), atol=1e-9) and np.allclose(np.linalg.det(r), 1)


def _max_depth_mm(renderer, poses):
    """Deepest penetration of the object through the gel plane in view, mm (full res)."""
    z = renderer.surface_z(poses).reshape(len(poses), -1).min(axis=1)
    return -z * 1000.0


def test_tracking_motion(renderer):
    m = make_motion(renderer, "tracking", n_frames=80, seed=1)
    p = m.object_T_sensor
    assert p.shape == (80, 4, 4) and p.dtype == np.float64 and _is_rigid(p)
    assert not m.pressed[:10].any() and m.pressed[10:].all()
    depth = _max_depth_mm(renderer, p[::7])
    pressed = m.pressed[::7]
    assert (depth[~pressed] < 0).all()  # lead-in: a gap, no contact
    assert (depth[pressed] > 0.3 - 0.02).all() and (depth[pressed] < 1.5 + 0.02).all()
    # the gel is tangent: the sensor z axis follows the inward surface normal, so the
    # view axis points at the object centre roughly (convex object)
    out = renderer.render(p[[0, 40, 79]])
    assert out.in_contact.tolist() == [False, True, True]
    # consecutive poses move smoothly (25 Hz hand motion: well below 1 mm per frame)
    step = np.linalg.norm(np.diff(p[10:, :3, 3], axis=0), axis=1)
    assert step.max() < 0.5e-3


@pytest.mark.parametrize("obj", ["shell", "dice"])
def test_no_jumps_over_texture(obj):
    """On ribs and pips the sensor glides: no frame's step is more than twice the median
    step of the seven frames around it. The closest surface point to a smooth path used to
    cling to a crest and jump a texture period in one frame (6.3x the local median on the
    shell, 4.3x on the dice), which NormalFlow aliased to the wrong crest."""
    from scipy.ndimage import median_filter

    m = make_motion(GelRenderer(make_object(obj)), "tracking", n_frames=200, seed=0)
    step = np.linalg.norm(np.diff(m.object_T_sensor[10:, :3, 3], axis=0), axis=1)
    assert (step / median_filter(step, size=7, mode="nearest")).max() < 2.0


def test_contact_loss_protocol(renderer):
    m = make_motion(renderer, "contact_loss", n_frames=130, seed=0)
    i = np.arange(130) - 10
    expected = (i >= 0) & (i % 100 < 75)
    assert np.array_equal(m.pressed, expected)
    probe = [10, 84, 85, 109, 110, 129]
    out = renderer.render(m.object_T_sensor[probe])
    assert out.in_contact.tolist() == [True, True, False, False, True, True]


def test_tracking_same_motion_with_and_without_loss(renderer):
    a = make_motion(renderer, "tracking", n_frames=120, seed=2)
    b = make_motion(renderer, "contact_loss", n_frames=120, seed=2)
    keep = b.pressed
    assert np.allclose(a.object_T_sensor[keep], b.object_T_sensor[keep])


def test_scan_touches_cover_and_break(renderer):
    cfg = MotionConfig()
    m = make_motion(renderer, "scan", n_frames=400, seed=0, config=cfg)
    p = m.object_T_sensor
    assert p.shape == (400, 4, 4) and _is_rigid(p)
    # several touches separated by contact-free stretches
    starts = np.flatnonzero(np.diff(m.pressed.astype(int)) == 1)
    assert len(starts) >= 4
    # air frames (not pressed and not in an approach/retract ramp) are contact-free
    air = ~m.pressed
    for k in range(1, cfg.approach_frames + 1):
        air &= ~np.roll(m.pressed, k) & ~np.roll(m.pressed, -k)
    idx = np.flatnonzero(air)[::5]
    assert (_max_depth_mm(renderer, p[idx]) < 0).all()
    # touches are spread over the object: contact points span most of its size
    centre = renderer.centre
    z = p[m.pressed, :3, 2]
    assert np.linalg.svd(z - z.mean(0), compute_uv=False).min() > 0.1  # view directions span 3-D
    assert np.linalg.norm(p[m.pressed, :3, 3] - centre, axis=1).max() < renderer.radius + 2e-3


def test_deterministic_and_seed_dependent(renderer):
    a = make_motion(renderer, "tracking", n_frames=40, seed=5).object_T_sensor
    b = make_motion(renderer, "tracking", n_frames=40, seed=5).object_T_sensor
    c = make_motion(renderer, "tracking", n_frames=40, seed=6).object_T_sensor
    assert np.array_equal(a, b) and not np.allclose(a, c)


def test_helpers():
    n = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0]])
    e1, e2 = tangent_basis(n, np.array([[1.0, 0, 0.5], [0, 0, 1.0]]))  # second hint parallel to n
    assert np.allclose(np.sum(e1 * n, 1), 0) and np.allclose(np.linalg.norm(e1, axis=1), 1)
    assert np.allclose(np.cross(n, e1), e2)
    assert np.allclose(e1[0], [1, 0, 0])
    x = transported_x(np.array([[0, 0, 1.0], [0, np.sin(0.1), np.cos(0.1)]]), np.array([1.0, 0, 0]))
    assert np.allclose(x[1], [1, 0, 0])
    p = np.eye(4)[None]
    assert np.allclose(lift(p, 0.002)[0, :3, 3], [0, 0, -0.002])


def test_errors(renderer):
    with pytest.raises(MotionError, match="kind"):
        make_motion(renderer, "orbit")
    with pytest.raises(MotionError, match="10000"):
        make_motion(renderer, "long", n_frames=500)
    with pytest.raises(MotionError, match="at least"):
        make_motion(renderer, "tracking", n_frames=5)
    with pytest.raises(MotionError, match="at least"):
        make_motion(renderer, "scan", n_frames=20)


@pytest.mark.parametrize("field, value, message", [
    ("max_step_deg", 0.0, "max_step_deg must be a finite number > 0"),
    ("max_step_deg", float("nan"), "max_step_deg must be a finite number > 0"),
    ("max_step_mm", -1.0, "max_step_mm must be a finite number > 0"),
    ("max_step_mm", float("inf"), "max_step_mm must be a finite number > 0"),
    ("lift_mm", 0.0, "lift_mm"),
    ("twist_deg", float("nan"), "twist_deg must be a finite number >= 0"),
    ("depth_mm", (1.5, 0.3), "lo <= hi"),
    ("depth_mm", (0.0, 1.0), "depths > 0"),
    ("touch_frames", (0, 10), "1 <= lo <= hi"),
    ("lead_in", -1, "lead_in must be >= 0"),
    ("press_stride", 0, "press_stride"),
    ("loss_length", 100, "must exceed loss_length"),
    ("guide_scales", (2.0, 0.0), "guide_scales must be finite smoothing multiples > 0"),
    ("guide_scales", (float("nan"),), "guide_scales"),
    ("slow_downs", (0.5, 1.5), r"slow_downs must be finite speeds in \(0, 1\]"),
    ("slow_downs", (0.0,), "slow_downs"),
])
def test_config_rejects_bad_values(field, value, message):
    with pytest.raises(MotionError, match=message):
        MotionConfig(**{field: value})


def test_config_accepts_the_edges():
    """Re-planning off (empty tuples), full speed as a 'slow-down' and zero amplitudes are
    valid; so are the defaults."""
    MotionConfig()
    MotionConfig(guide_scales=(), slow_downs=(1.0,), twist_deg=0.0, roll_deg=0.0, approach_frames=0)


def test_surface_guide_rejects_bad_points_and_scales():
    guide = SurfaceGuide(_groove(half_mm=2.0), smoothing_m=2e-4)
    with pytest.raises(ValueError, match=r"shape \(N, 3\)"):
        guide.project(np.zeros((4, 2)))
    with pytest.raises(ValueError, match=r"shape \(N, 3\)"):
        guide.walk(np.zeros((5, 6)))
    with pytest.raises(ValueError, match="NaN or Inf"):
        guide.walk(np.array([[0.0, 0.0, 1e-3], [np.nan, 0.0, 1e-3]]))
    with pytest.raises(ValueError, match="finite number > 0"):
        guide.project(np.zeros((1, 3)), scale=0.0)
    with pytest.raises(ValueError, match="too coarse"):
        guide.project(np.zeros((1, 3)), scale=1e4)  # 2 m cells on a 4 mm patch
    points, normals = guide.walk(np.zeros((0, 3)))
    assert points.shape == normals.shape == (0, 3)
    one, _ = guide.project(np.array([0.5e-3, 0.0, 2e-3]))  # a single point (3,) is one row
    assert one.shape == (1, 3) and one[0, 2] == pytest.approx(abs(one[0, 0]), abs=1e-6)


def test_small_objects_skip_fields_coarser_than_themselves():
    """On a 2 mm ball the 8x normal field (6.4 mm cells) leaves no triangles. A path that
    must try every candidate (a limit no path meets) skips that field and keeps the
    plausiblest of the rest instead of failing; the guide says which fields exist."""
    ball = o3d.geometry.TriangleMesh.create_sphere(1e-3, 60)
    ball.compute_vertex_normals()
    guide = SurfaceGuide(ball)
    assert guide.resolves(2.0) and guide.resolves(4.0) and not guide.resolves(8.0)
    renderer, strict = GelRenderer(ball), MotionConfig(max_step_deg=1e-3)
    m = make_motion(renderer, "tracking", 60, 0, strict)
    plain = make_motion(renderer, "tracking", 60, 0, MotionConfig(max_step_deg=1e-3, guide_scales=(), slow_downs=()))
    assert m.paths == 1 and _is_rigid(m.object_T_sensor)
    fast = too_fast(m.object_T_sensor, m.pressed, strict).sum()
    assert 0 < fast <= too_fast(plain.object_T_sensor, plain.pressed, strict).sum()  # none plausible; the fewest kept


PLAIN = MotionConfig(guide_scales=(), slow_downs=())  # every path as planned, however fast


def _groove(slope: float = 1.0, half_mm: float = 8.0, step_mm: float = 0.1) -> o3d.geometry.TriangleMesh:
    """A V groove ``z = slope |x|`` (metres), 2 * half_mm square, triangulated on a grid."""
    g = np.arange(-half_mm, half_mm + 1e-9, step_mm) * 1e-3
    x, y = np.meshgrid(g, g, indexing="ij")
    v = np.stack([x, y, slope * np.abs(x)], -1).reshape(-1, 3)
    n = len(g)
    i, j = np.meshgrid(np.arange(n - 1), np.arange(n - 1), indexing="ij")
    a, b, c, d = i * n + j, (i + 1) * n + j, (i + 1) * n + j + 1, i * n + j + 1
    tri = np.concatenate([np.stack([a, c, b], -1).reshape(-1, 3), np.stack([a, d, c], -1).reshape(-1, 3)])
    return o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(v), o3d.utility.Vector3iVector(tri))


def test_walk_crosses_a_groove_without_jumping():
    """Targets 2 mm above a 90 deg groove, moving across it in 0.1 mm steps: the closest
    points jump from one wall to the other at the medial plane (by 2 mm: the feet at
    x = -1 and +1 mm, computed by hand), while the walk stays on the surface and moves
    about one step per target."""
    guide = SurfaceGuide(_groove(), smoothing_m=2e-4)
    xs = np.arange(-3.0, 3.0 + 1e-9, 0.1) * 1e-3
    targets = np.stack([xs, np.zeros_like(xs), np.full_like(xs, 2e-3)], -1)
    proj, _ = guide.project(targets)
    walk, normals = guide.walk(targets)
    jump = np.linalg.norm(np.diff(proj, axis=0), axis=1).max()
    assert jump == pytest.approx(2e-3, rel=0.05)  # (-1, 1) -> (1, 1) mm in (x, z)
    steps = np.linalg.norm(np.diff(walk, axis=0), axis=1)
    assert steps.max() < 0.15e-3 and steps.min() > 0.05e-3
    assert np.allclose(walk[:, 2], np.abs(walk[:, 0]), atol=1e-6)  # on the surface
    assert walk[0, 0] < -1e-3 and walk[-1, 0] > 1e-3  # it crossed
    assert np.allclose(np.linalg.norm(normals, axis=1), 1.0)


def test_too_fast_counts_only_touching_steps():
    poses = np.tile(np.eye(4), (4, 1, 1))
    poses[1, 0, 3] = 2e-3  # 2 mm in one frame, then back
    touching = np.array([True, True, False, False])
    assert too_fast(poses, touching, MotionConfig()).tolist() == [True, False, False]
    assert not too_fast(poses, np.array([True, False, True, True]), MotionConfig()).any()


@pytest.mark.parametrize("name", ["seed", "rock"])
def test_paths_faster_than_a_hand_are_replanned(name):
    """As planned, a scan round the small seed (tight curvature) and a slide over the rock
    (deep relief, concavities) turn or move the pressed sensor faster than a hand in some
    frames; re-planned, no step does, and the motion says how many paths it re-planned."""
    if name == "seed":
        renderer, kind, n = GelRenderer(make_object("seed", resolution_mm=0.1)), "scan", 400
    else:
        renderer, kind, n = GelRenderer(make_heldout("rock", 0.25, 0)), "tracking", 200
    plain, fixed = make_motion(renderer, kind, n, 0, PLAIN), make_motion(renderer, kind, n, 0)
    assert too_fast(plain.object_T_sensor, plain.pressed, MotionConfig()).sum() > 0
    assert too_fast(fixed.object_T_sensor, fixed.pressed, MotionConfig()).sum() == 0
    assert 0 < fixed.replanned <= fixed.paths and plain.replanned == 0
    assert np.array_equal(plain.pressed, fixed.pressed)
    assert _is_rigid(fixed.object_T_sensor)


def test_plausible_paths_stay_as_planned():
    """The lime's tracking path never moves faster than a hand, so re-planning leaves
    every pose bit for bit as planned."""
    renderer = GelRenderer(make_object("lime"))
    plain, fixed = make_motion(renderer, "tracking", 150, 1, PLAIN), make_motion(renderer, "tracking", 150, 1)
    assert np.array_equal(plain.object_T_sensor, fixed.object_T_sensor)
    assert fixed.replanned == 0 and fixed.paths == 1
