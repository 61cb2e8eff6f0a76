"""Test oracle: keyframes of an analytic sphere pressed into the gel at known poses.

In each keyframe's sensor frame the sphere's centre sits at ``(cx, cy, R - depth)``, so
its lowest point is ``depth`` below the undeformed gel (z = 0, pressing negative). The
gel height is ``min(0, cz - sqrt(R^2 - (x-cx)^2 - (y-cy)^2))``, its exact slopes are
passed to ``FrameBuilder.from_gradients`` with the eroded contact, and the pose
``world_T_kf`` is known exactly (the sphere's centre is the world origin).
"""

from __future__ import annotations

import math

import numpy as np
import open3d as o3d
import torch

from tactile_slam.config import Config
from tactile_slam.geometry.frame import FrameBuilder
from tactile_slam.geometry.morphology import erode
from tactile_slam.tracking.keyframe import Keyframe


def fibonacci_directions(n: int) -> np.ndarray:
    """``(n, 3)`` near-uniform unit vectors."""
    k = np.arange(n) + 0.5
    phi = np.arccos(1 - 2 * k / n)
    theta = math.pi * (1 + 5**0.5) * k
    return np.stack([np.cos(theta) * np.sin(phi), np.sin(theta) * np.sin(phi), np.cos(phi)], 1)


def sensor_pose(direction: np.ndarray, radius_m: float, depth_m: float, spin: float) -> np.ndarray:
    """``world_T_kf`` of a sensor touching the sphere at ``direction`` (outward unit).
    The sensor's z axis points into the sphere; ``spin`` rotates it about that axis."""
    z = -direction / np.linalg.norm(direction)
    helper = np.array([1.0, 0, 0]) if abs(z[0]) < 0.9 else np.array([0, 1.0, 0])
    x = np.cross(helper, z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    c, s = math.cos(spin), math.sin(spin)
    x, y = c * x + s * y, -s * x + c * y
    T = np.eye(4)
    T[:3, :3] = np.stack([x, y, z], 1)
    T[:3, 3] = -z * (radius_m - depth_m)
    return T


def sphere_keyframes(
    config: Config, radius_mm: float, depth_mm: float, n: int, seed: int = 0
) -> tuple[list[Keyframe], torch.Tensor]:
    """Keyframes of ``n`` presses spread over the sphere, and their ``(n, 4, 4)`` float64
    poses in the world frame (sphere centre at the origin), metres."""
    rng = np.random.default_rng(seed)
    h_px, w_px = config.sensor.shape
    s_mm = config.sensor.mm_per_px
    xs = (np.arange(w_px) - (w_px - 1) / 2) * s_mm
    ys = (np.arange(h_px) - (h_px - 1) / 2) * s_mm
    X, Y = np.meshgrid(xs, ys)
    cz = radius_mm - depth_mm
    r2 = X**2 + Y**2
    inside = r2 < radius_mm**2
    root = np.sqrt(np.clip(radius_mm**2 - r2, 1e-12, None))
    zlow = np.where(inside, cz - root, np.inf)
    pressed = zlow < 0
    height_mm = np.where(pressed, zlow, 0.0)
    grad = np.stack([np.where(pressed, X / root, 0.0), np.where(pressed, Y / root, 0.0)], -1)
    contact = torch.from_numpy(height_mm < -0.05)[None]
    contact = erode(contact, max(h_px // 48, 1), border_is_contact=False)
    builder = FrameBuilder(config)
    frames = builder.from_gradients(torch.from_numpy(grad).float()[None].expand(n, -1, -1, -1).contiguous(),
                                    contact=contact.expand(n, -1, -1).contiguous())
    poses, kfs = [], []
    for i, d in enumerate(fibonacci_directions(n)):
        poses.append(sensor_pose(d, radius_mm / 1000, depth_mm / 1000, rng.uniform(0, 2 * math.pi)))
        kfs.append(Keyframe(id=i, session=0, maps=frames[i], new_session=i == 0,
                            prev_T_kf=torch.eye(4, dtype=torch.float64)))
    return kfs, torch.from_numpy(np.stack(poses))


def sphere_chamfer_mm(vertices: np.ndarray, faces: np.ndarray, radius_mm: float, n: int = 20000,
                      seed: int = 0) -> tuple[float, float]:
    """(accuracy, completeness) in mm of a mesh in metres against the sphere at the origin:
    mean |r - R| of the vertices, and the mean distance from uniform sphere samples to
    the mesh."""
    v_mm = vertices * 1000.0
    acc = float(np.abs(np.linalg.norm(v_mm, axis=1) - radius_mm).mean())
    rng = np.random.default_rng(seed)
    q = rng.normal(size=(n, 3))
    q = q / np.linalg.norm(q, axis=1, keepdims=True) * radius_mm
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(v_mm.astype(np.float32)), o3d.core.Tensor(faces.astype(np.uint32)))
    comp = float(scene.compute_distance(o3d.core.Tensor(q.astype(np.float32))).numpy().mean())
    return acc, comp
