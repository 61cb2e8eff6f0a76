"""Sensor motions over an object: the four episode kinds with ground-truth poses.

Every pose is ``object_T_sensor`` (the sensor's pose in the object frame, metres,
float64; method.md section 1.4). A pressed pose puts the gel tangent to the surface:
the sensor's z axis is the inward smoothed surface normal at the contact point, and the
sensor is then slid along its own z axis until the deepest point of the object in its
field of view sits exactly ``depth`` below the gel plane (a coarse ray cast, exact for a
translation along the rays). Lifting moves the sensor back along -z.

Kinds (the first ``lead_in`` frames of every kind are contact-free, the sensor held
above its first contact, because recordings take their background from them):

* ``tracking``: one continuous contact; the contact point follows a smooth periodic
  (Lissajous) path on the surface, so earlier regions are revisited, with in-plane
  twist, small rolls and indentation varying in 0.3-1.5 mm; the cumulative motion per
  axis of a 500-frame episode is of the order of the paper's Table I (tens of degrees
  and of millimetres, measured by :func:`tactile_slam.eval.tracking_metrics.motion_range`).
* ``contact_loss``: the same motion, lifted off the object for the frames whose
  index after the lead-in satisfies ``i mod 100 >= 75`` (25 of every 100 frames, the
  paper's protocol); the motion goes on in the air, so contact resumes elsewhere.
* ``scan``: hand-held reconstruction scan, many short touches (approach, a short slide
  with twist and roll, retract) at farthest-point-sampled surface locations visited in
  a nearest-neighbour order, with air moves between touches that leave the object's
  bounding sphere; together the touches cover the whole object.
* ``long``: the same as ``scan`` with at least 10,000 frames (denser, revisited cover).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.ndimage import gaussian_filter1d
from scipy.spatial.transform import Rotation, Slerp

from tactile_slam.eval.tracking_metrics import frame_steps
from tactile_slam.sim.renderer import GelRenderer
from tactile_slam.sim.surface import SurfaceGuide, farthest_points, sample_surface

KINDS = ("tracking", "contact_loss", "scan", "long")
MOTION_REVISION = 3
"""Bumped whenever the same settings and seed give other poses, so that cached episodes
made by an earlier motion are simulated again. 2 (2026-11-29): touch paths smoothed over
time (:func:`_path_poses`). 3 (2026-12-03): paths faster than a hand re-planned (walked,
coarser normals, slower; :func:`_path_poses`); paths that were plausible are unchanged."""
DEFAULT_FRAMES = {"tracking": 520, "contact_loss": 520, "scan": 3000, "long": 10000}


class MotionError(ValueError):
    """Invalid motion parameters."""


@dataclass
class MotionConfig:
    """Motion parameters (lengths in mm, angles in degrees at this user-facing edge).

    Attributes:
        lead_in: contact-free frames at the start of every episode.
        depth_mm: indentation range while touching.
        lift_mm: clearance of contact-free frames above the object.
        twist_deg: amplitude of the in-plane twist during tracking.
        roll_deg: amplitude of the rolls about the sensor's x and y axes.
        path_mm: amplitude of the tracking path (capped at 0.15 x object size, so small
            curved objects are not rolled over end to end).
        cycles: path oscillations per 500 tracking frames.
        touch_frames: range of contact frames per scan touch.
        approach_frames / air_frames: frames per approach (and retract) / air move.
        loss_period / loss_length: contact-loss protocol (frames).
        press_stride: pixel stride of the ray grid that sets the indentation.
        max_step_deg / max_step_mm: the fastest a hand moves the pressed sensor in one
            frame (125 deg/s and 25 mm/s at 25 fps, the tracker's motion limits).
        guide_scales: coarser normal fields (multiples of the surface guide's smoothing)
            tried, with the path walked along the surface, for a path that moves faster
            than that on the plain closest points (non-convex or very rough meshes).
        slow_downs: slower speeds along the same path, tried (each with every normal
            field) when no field makes it plausible (tight curvature: a fast slide round a
            small object turns the sensor too fast whatever the smoothing).
    """

    lead_in: int = 10
    depth_mm: tuple[float, float] = (0.3, 1.5)
    lift_mm: float = 1.0
    twist_deg: float = 12.0
    roll_deg: float = 3.0
    path_mm: float = 6.0
    cycles: float = 2.0
    touch_frames: tuple[int, int] = (35, 65)
    approach_frames: int = 5
    air_frames: int = 10
    loss_period: int = 100
    loss_length: int = 25
    press_stride: int = 6
    max_step_deg: float = 5.0
    max_step_mm: float = 1.0
    guide_scales: tuple[float, ...] = (2.0, 4.0, 8.0)
    slow_downs: tuple[float, ...] = (0.5, 0.25)

    def __post_init__(self) -> None:
        def finite(name: str, values: tuple[float, ...], ok, rule: str) -> None:
            if not all(np.isfinite(v) and ok(v) for v in values):
                raise MotionError(f"MotionConfig.{name} must be {rule}, got {getattr(self, name)!r}")

        for name in ("lift_mm", "max_step_deg", "max_step_mm"):
            finite(name, (getattr(self, name),), lambda v: v > 0, "a finite number > 0")
        for name in ("twist_deg", "roll_deg", "path_mm", "cycles"):
            finite(name, (getattr(self, name),), lambda v: v >= 0, "a finite number >= 0")
        finite("depth_mm", self.depth_mm, lambda v: v > 0, "two finite depths > 0 (lo, hi)")
        if len(self.depth_mm) != 2 or self.depth_mm[0] > self.depth_mm[1]:
            raise MotionError(f"MotionConfig.depth_mm must be (lo, hi) with lo <= hi, got {self.depth_mm!r}")
        if len(self.touch_frames) != 2 or not 1 <= self.touch_frames[0] <= self.touch_frames[1]:
            raise MotionError(f"MotionConfig.touch_frames must be (lo, hi) with 1 <= lo <= hi, got {self.touch_frames!r}")
        for name in ("lead_in", "approach_frames", "air_frames", "loss_length"):
            if getattr(self, name) < 0:
                raise MotionError(f"MotionConfig.{name} must be >= 0 frames, got {getattr(self, name)!r}")
        if self.press_stride < 1:
            raise MotionError(f"MotionConfig.press_stride must be >= 1 pixel, got {self.press_stride!r}")
        if not self.loss_period > self.loss_length:
            raise MotionError(f"MotionConfig.loss_period ({self.loss_period}) must exceed loss_length "
                              f"({self.loss_length}), or no frame of a contact-loss episode touches")
        finite("guide_scales", tuple(self.guide_scales), lambda v: v > 0, "finite smoothing multiples > 0")
        finite("slow_downs", tuple(self.slow_downs), lambda v: 0 < v <= 1, "finite speeds in (0, 1]")


@dataclass
class Motion:
    """A motion: ``object_T_sensor`` ``(T, 4, 4)`` float64 metres and ``pressed``
    ``(T,)`` bool, the frames where the motion intends contact; ``paths`` contact paths
    (touches), ``replanned`` of them moved too fast as planned and were re-planned
    (:func:`_path_poses`)."""

    object_T_sensor: np.ndarray
    pressed: np.ndarray
    kind: str
    paths: int = 1
    replanned: int = 0


# ---------------------------------------------------------------- pose building


def _smooth_series(t: np.ndarray, rng: np.random.Generator, cycles: float, amp: float, n_terms: int = 2) -> np.ndarray:
    """Sum of sinusoids with random phases starting at 0, amplitude ~``amp``. ``(T,)``."""
    out = np.zeros_like(t)
    weights = np.array([0.7, 0.3, 0.2][:n_terms])
    for w, f in zip(weights, cycles * np.array([rng.uniform(0.7, 1.2), rng.uniform(1.6, 2.6), 3.1][:n_terms])):
        phase = rng.uniform(0, 2 * np.pi)
        out += w * amp * (np.sin(2 * np.pi * f * t + phase) - np.sin(phase))
    return out


def tangent_basis(normal: np.ndarray, hint: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit tangents ``(e1, e2)`` ``(N, 3)`` of ``normal`` ``(N, 3)``; ``e1`` is ``hint``
    projected on the tangent plane (another axis where they are parallel)."""
    e1 = hint - np.sum(hint * normal, -1, keepdims=True) * normal
    bad = np.linalg.norm(e1, axis=-1) < 1e-6
    if bad.any():
        alt = np.where(np.abs(normal[bad, 0:1]) < 0.9, [[1.0, 0, 0]], [[0, 1.0, 0]])
        e1[bad] = alt - np.sum(alt * normal[bad], -1, keepdims=True) * normal[bad]
    e1 /= np.linalg.norm(e1, axis=-1, keepdims=True)
    return e1, np.cross(normal, e1)


def pressed_poses(renderer: GelRenderer, points: np.ndarray, normals: np.ndarray, x_hint: np.ndarray,
                  twist: np.ndarray, roll_x: np.ndarray, roll_y: np.ndarray, depth_m: np.ndarray,
                  stride: int = 6) -> np.ndarray:
    """Sensor poses touching the surface.

    The sensor's z axis is ``-normals`` (toward the object), its x axis ``x_hint``
    projected on the gel plane; then it is twisted about z by ``twist`` and rolled by
    ``roll_x`` then ``roll_y`` (rad, about its own axes), and finally slid along z so the
    object's deepest point in view is ``depth_m`` below the gel (negative: a gap).

    Args:
        points: ``(T, 3)`` contact points, metres, object frame.
        normals: ``(T, 3)`` outward unit normals there.
        x_hint: ``(T, 3)`` preferred sensor x axes.
        twist, roll_x, roll_y, depth_m: ``(T,)``.

    Returns:
        ``(T, 4, 4)`` ``object_T_sensor``.
    """
    z = -normals
    x, y = tangent_basis(z, x_hint)
    base = np.stack([x, y, z], -1)  # columns are the sensor axes
    local = Rotation.from_euler("ZXY", np.stack(np.broadcast_arrays(twist, roll_x, roll_y), -1)).as_matrix()
    poses = np.tile(np.eye(4), (len(points), 1, 1))
    poses[:, :3, :3] = base @ local
    poses[:, :3, 3] = points
    grid = renderer.pixel_xy[stride // 2::stride, stride // 2::stride]
    zmin = renderer.surface_z(poses, grid).reshape(len(poses), -1).min(axis=1)
    zmin = np.where(np.isfinite(zmin), zmin, 0.0)
    poses[:, :3, 3] += (zmin + depth_m)[:, None] * poses[:, :3, 2]
    return poses


def lift(poses: np.ndarray, distance_m: float | np.ndarray) -> np.ndarray:
    """Move ``(T, 4, 4)`` sensor poses back along their own -z by ``distance_m``."""
    out = poses.copy()
    out[:, :3, 3] -= np.broadcast_to(np.asarray(distance_m, dtype=np.float64), (len(poses),))[:, None] * poses[:, :3, 2]
    return out


def transported_x(normals: np.ndarray, x0: np.ndarray) -> np.ndarray:
    """Parallel transport of a tangent direction along a sequence of normals ``(T, 3)``
    -> ``(T, 3)`` x hints that do not spin as the normal changes."""
    out = np.empty_like(normals)
    x = x0
    for i, n in enumerate(normals):
        x = x - np.dot(x, n) * n
        x = x / np.linalg.norm(x)
        out[i] = x
    return out


def _path_poses(renderer, guide, t, p0, n0, e1, e2, amp_m, cycles, twist, rolls, depth_m, rng, cfg):
    """Poses following a periodic path of amplitude ``amp_m`` around ``p0``.

    The closest surface points and their normals are both smoothed over time (a Gaussian
    of 2 frames). On a textured surface the closest point to a smooth path clings to the
    nearest crest and then jumps to the next one, a texture period in one frame (up to
    0.44 mm against a median step of 0.02-0.07 mm); a hand-held sensor glides over the
    crests instead. The depth is set afterwards against the true surface.

    Where those poses move faster than a hand (:func:`too_fast`: across a concavity the
    closest point jumps to another sheet, deep relief turns the normal by tens of degrees
    per frame, a fast slide round a tight curve turns the sensor with it), the path is
    walked along the surface instead (:meth:`SurfaceGuide.walk`) with each coarser normal
    field of ``cfg.guide_scales`` in turn (those that resolve the object:
    :meth:`SurfaceGuide.resolves`), then all of it again at each slower speed of
    ``cfg.slow_downs`` (the same path, covered more slowly), and the first plausible
    candidate is kept (else the one with the fewest too-fast steps). A path that is
    plausible as it is stays exactly as it was."""
    u = np.stack([_smooth_series(t, rng, cycles, amp_m), _smooth_series(t, rng, cycles, amp_m)], -1)
    touching = np.asarray(depth_m) > 0
    frames = np.arange(len(t), dtype=np.float64)
    best, best_count, best_key = None, None, None
    for speed in (1.0, *cfg.slow_downs):
        us = u if speed == 1.0 else np.stack([np.interp(speed * frames, frames, c) for c in u.T], -1)
        targets = p0 + us[:, :1] * e1 + us[:, 1:] * e2
        for scale in (None, *cfg.guide_scales):
            if scale is not None and not guide.resolves(scale):  # built only when a path needs it
                continue
            points, normals = guide.project(targets) if scale is None else guide.walk(targets, scale)
            points = gaussian_filter1d(points, 2.0, axis=0, mode="nearest")
            normals = gaussian_filter1d(normals, 2.0, axis=0, mode="nearest")
            normals /= np.linalg.norm(normals, axis=1, keepdims=True)
            xh = transported_x(-normals, e1)
            poses = pressed_poses(renderer, points, normals, xh, twist, rolls[0], rolls[1], depth_m, cfg.press_stride)
            count = too_fast(poses, touching, cfg).sum()
            if best is None or count < best_count:
                best, best_count, best_key = poses, count, (speed, scale)
            if count == 0:
                break
        if best_count == 0:
            break
    return best, best_key != (1.0, None)


def too_fast(poses: np.ndarray, touching: np.ndarray, cfg: MotionConfig) -> np.ndarray:
    """``(T - 1,)`` bool: steps between consecutive ``touching`` frames of ``poses``
    ``(T, 4, 4)`` that turn by more than ``cfg.max_step_deg`` or move by more than
    ``cfg.max_step_mm``."""
    deg, mm = frame_steps(poses, touching)
    with np.errstate(invalid="ignore"):
        return (deg > cfg.max_step_deg) | (mm > cfg.max_step_mm)


def _object_size(renderer: GelRenderer) -> float:
    return 2.0 * renderer.radius


def tracking_motion(renderer: GelRenderer, n_frames: int = 520, seed: int = 0, contact_loss: bool = False,
                    config: MotionConfig | None = None, guide: SurfaceGuide | None = None) -> Motion:
    """Continuous-contact tracking motion (``contact_loss``: the paper's periodic lifts).

    Returns:
        :class:`Motion` with ``n_frames`` poses; frames ``0..lead_in-1`` contact-free.
    """
    cfg = config or MotionConfig()
    if n_frames < cfg.lead_in + 2:
        raise MotionError(f"a tracking episode needs at least {cfg.lead_in + 2} frames, got {n_frames}")
    rng = np.random.default_rng(seed)
    guide = guide or SurfaceGuide(renderer.mesh)
    n = n_frames - cfg.lead_in
    t = np.arange(n) / 500.0
    p_start, _ = sample_surface(renderer.mesh, 1, rng)
    p0, n0 = guide.project(p_start)
    e1, e2 = tangent_basis(n0, rng.normal(size=(1, 3)))
    amp = min(cfg.path_mm * 1e-3, 0.15 * _object_size(renderer))
    twist = np.deg2rad(_smooth_series(t, rng, 0.7 * cfg.cycles, cfg.twist_deg))
    rolls = [np.deg2rad(_smooth_series(t, rng, cfg.cycles, cfg.roll_deg)) for _ in range(2)]
    lo, hi = cfg.depth_mm
    mid, half = 0.5 * (lo + hi), 0.5 * (hi - lo)
    depth = mid + half * np.sin(2 * np.pi * rng.uniform(1.5, 3.0) * t * cfg.cycles / 1.6 + rng.uniform(0, 2 * np.pi))
    poses, replanned = _path_poses(renderer, guide, t, p0, n0, e1, e2, amp, cfg.cycles, twist, rolls, depth * 1e-3,
                                   rng, cfg)
    pressed = np.ones(n, dtype=bool)
    if contact_loss:
        pressed = (np.arange(n) % cfg.loss_period) < cfg.loss_period - cfg.loss_length
        poses[~pressed] = lift(poses[~pressed], (depth[~pressed] + cfg.lift_mm) * 1e-3)
    lead = lift(np.repeat(poses[:1], cfg.lead_in, axis=0), (depth[0] + 2 * cfg.lift_mm) * 1e-3)
    return Motion(np.concatenate([lead, poses]), np.concatenate([np.zeros(cfg.lead_in, bool), pressed]),
                  "contact_loss" if contact_loss else "tracking", 1, int(replanned))


def _air_path(a: np.ndarray, b: np.ndarray, n: int, centre: np.ndarray, far: float) -> np.ndarray:
    """``n`` poses from ``a`` to ``b`` (both lifted, ``(4, 4)``): back out along a's -z to
    ``far`` from the centre, round a great circle, then in along b's -z."""
    def out_point(p):
        d = -p[:3, 2]
        o = p[:3, 3] - centre
        # distance along d that puts the sensor at ``far`` from the centre
        k = -np.dot(o, d) + np.sqrt(max(np.dot(o, d) ** 2 - np.dot(o, o) + far ** 2, 0.0))
        return p[:3, 3] + k * d
    fa, fb = out_point(a), out_point(b)
    s = (np.arange(n) + 1) / (n + 1)
    leg = np.clip(s / 0.25, 0, 1)[:, None], np.clip((s - 0.75) / 0.25, 0, 1)[:, None]
    mid = np.clip((s - 0.25) / 0.5, 0, 1)
    ua, ub = (fa - centre) / np.linalg.norm(fa - centre), (fb - centre) / np.linalg.norm(fb - centre)
    omega = np.arccos(np.clip(np.dot(ua, ub), -1, 1))
    if omega < 1e-6:
        arc = np.outer(1 - mid, ua) + np.outer(mid, ub)
    else:
        arc = (np.outer(np.sin((1 - mid) * omega), ua) + np.outer(np.sin(mid * omega), ub)) / np.sin(omega)
    arc = centre + far * arc / np.linalg.norm(arc, axis=1, keepdims=True)
    pos = np.where(s[:, None] < 0.25, a[:3, 3] + leg[0] * (fa - a[:3, 3]),
                   np.where(s[:, None] > 0.75, fb + leg[1] * (b[:3, 3] - fb), arc))
    rots = Slerp([0, 1], Rotation.from_matrix(np.stack([a[:3, :3], b[:3, :3]])))(s).as_matrix()
    out = np.tile(np.eye(4), (n, 1, 1))
    out[:, :3, :3] = rots
    out[:, :3, 3] = pos
    return out


def scan_motion(renderer: GelRenderer, n_frames: int = 3000, seed: int = 0, config: MotionConfig | None = None,
                guide: SurfaceGuide | None = None, kind: str = "scan") -> Motion:
    """Hand-held scan: short touches covering the object, with contact breaks.

    Returns:
        :class:`Motion` with exactly ``n_frames`` poses.
    """
    cfg = config or MotionConfig()
    per_touch = 2 * cfg.approach_frames + cfg.air_frames + sum(cfg.touch_frames) // 2
    if n_frames < cfg.lead_in + per_touch:
        raise MotionError(f"a scan needs at least {cfg.lead_in + per_touch} frames, got {n_frames}")
    rng = np.random.default_rng(seed)
    guide = guide or SurfaceGuide(renderer.mesh)
    n_touch = (n_frames - cfg.lead_in) // per_touch + 1
    cand, _ = sample_surface(renderer.mesh, max(20 * n_touch, 2000), rng)
    centres = cand[farthest_points(cand, n_touch, start=int(rng.integers(len(cand))))]
    order = _nearest_neighbour_tour(centres)
    far = renderer.radius * 2.0 + 5e-3
    lo, hi = cfg.depth_mm
    poses, pressed = [], []
    prev_end = None
    total = n_paths = n_replanned = 0
    for visit in range(10 * len(order)):  # the tour repeats if random touch lengths fall short
        if total >= n_frames:
            break
        k = order[visit % len(order)]
        m = int(rng.integers(cfg.touch_frames[0], cfg.touch_frames[1] + 1))
        na = cfg.approach_frames
        t = np.arange(m + 2 * na) / 500.0
        p0, n0 = guide.project(centres[k:k + 1])
        e1, e2 = tangent_basis(n0, rng.normal(size=(1, 3)))
        d = rng.uniform(lo, 0.85 * hi)
        ramp = np.clip(np.minimum(np.arange(m + 2 * na) + 1, m + 2 * na - np.arange(m + 2 * na)) / (na + 1), 0, 1)
        depth = (-cfg.lift_mm + ramp * (d + cfg.lift_mm)) * 1e-3
        twist = rng.uniform(-np.pi, np.pi) + np.deg2rad(_smooth_series(t, rng, 8.0, 0.6 * cfg.twist_deg, 1))
        rolls = [np.deg2rad(_smooth_series(t, rng, 8.0, 0.6 * cfg.roll_deg, 1)) for _ in range(2)]
        amp = rng.uniform(0.8e-3, 2.5e-3)
        touch, replanned = _path_poses(renderer, guide, t, p0, n0, e1, e2, amp, 8.0, twist, rolls, depth, rng, cfg)
        n_replanned += int(replanned)
        if prev_end is not None:
            poses.append(_air_path(prev_end, touch[0], cfg.air_frames, renderer.centre, far))
            pressed.append(np.zeros(cfg.air_frames, bool))
        else:
            poses.append(lift(np.repeat(touch[:1], cfg.lead_in, axis=0), cfg.lift_mm * 1e-3))
            pressed.append(np.zeros(cfg.lead_in, bool))
        poses.append(touch)
        pressed.append(ramp >= 1)
        prev_end = touch[-1]
        total = sum(len(p) for p in poses)
        n_paths += 1
    return Motion(np.concatenate(poses)[:n_frames], np.concatenate(pressed)[:n_frames], kind, n_paths, n_replanned)


def _nearest_neighbour_tour(points: np.ndarray) -> np.ndarray:
    """Greedy nearest-neighbour visiting order of ``(K, 3)`` points, from index 0."""
    left = np.ones(len(points), bool)
    order = [0]
    left[0] = False
    for _ in range(len(points) - 1):
        d = np.linalg.norm(points - points[order[-1]], axis=1)
        d[~left] = np.inf
        order.append(int(np.argmin(d)))
        left[order[-1]] = False
    return np.asarray(order)


def make_motion(renderer: GelRenderer, kind: str, n_frames: int | None = None, seed: int = 0,
                config: MotionConfig | None = None) -> Motion:
    """One of :data:`KINDS` with ``n_frames`` (default :data:`DEFAULT_FRAMES`)."""
    if kind not in KINDS:
        raise MotionError(f"unknown episode kind {kind!r}; choose one of {KINDS}")
    n = DEFAULT_FRAMES[kind] if n_frames is None else int(n_frames)
    if kind == "long" and n < 10000:
        raise MotionError(f"a long scan has at least 10000 frames, got {n}")
    guide = SurfaceGuide(renderer.mesh)
    if kind in ("tracking", "contact_loss"):
        return tracking_motion(renderer, n, seed, kind == "contact_loss", config, guide)
    return scan_motion(renderer, n, seed, config, guide, kind)
