"""Gel renderer: ray-cast an object mesh into GelSight height, gradient and contact maps.

Sensor frame (method.md section 1.2): x along image columns, y down the rows, z out of
the gel toward the object; the undeformed gel surface is the plane z = 0 and pixel
(r, c) looks along +z through ((c - (W-1)/2) s, (r - (H-1)/2) s, 0), s = mm_per_px/1000.

For each pose ``object_T_sensor`` (the sensor's pose in the object frame, metres) the
renderer casts one parallel ray per pixel along the sensor's +z axis with open3d's
``RaycastingScene``. Where the first surface hit lies at z < 0 the object penetrates the
gel plane; the gel follows it, so the raw height is ``min(z_hit, 0)``, clamped at the
sensor's maximum indentation. The elastomer then low-passes the indentation (Gaussian,
``elastomer_sigma_mm``): fine texture below ~0.1 mm is smoothed and the gel drapes a
little beyond the contact edge, as a real gel does. Gradients are the central
differences of that height (one-sided at the image border), so the exact Poisson
integrator recovers the height from them. Contact is where the smoothed indentation is
deeper than ``contact_depth_mm``, eroded with the pipeline's final erosion
(method.md section 3.2, border counts as non-contact).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import open3d as o3d
import torch
import torch.nn.functional as F

from tactile_slam.config import Config
from tactile_slam.geometry.morphology import dilate, erode


class RenderError(ValueError):
    """Bad poses or an unusable mesh given to the renderer."""


@dataclass
class RenderConfig:
    """Gel model parameters.

    Attributes:
        elastomer_sigma_mm: Gaussian low-pass of the indentation (elastomer smoothing).
        contact_depth_mm: indentation beyond which a pixel counts as in contact.
        cull_stride: pixel stride of the first pass that skips rays far from the gel
            (1 casts every pixel).
        cull_margin_mm: in the first pass, surfaces farther than this in front of the
            gel plane count as out of reach (texture relief and curvature sag between
            two first-pass samples must stay below it).
    """

    elastomer_sigma_mm: float = 0.1
    contact_depth_mm: float = 0.03
    cull_stride: int = 6
    cull_margin_mm: float = 0.5


@dataclass
class GelMaps:
    """Rendered maps of ``N`` frames (float32 on the renderer's device).

    Attributes:
        height: ``(N, H, W)`` px, undeformed gel at 0, pressed negative.
        gradients: ``(N, H, W, 2)`` ``(dh/dx, dh/dy)``.
        contact: ``(N, H, W)`` bool.
        in_contact: ``(N,)`` bool, contact area at least the config's minimum.
    """

    height: torch.Tensor
    gradients: torch.Tensor
    contact: torch.Tensor
    in_contact: torch.Tensor


def check_poses(poses: np.ndarray) -> np.ndarray:
    """Validate ``(N, 4, 4)`` or ``(4, 4)`` rigid transforms; returns ``(N, 4, 4)`` float64."""
    poses = np.asarray(poses, dtype=np.float64)
    if poses.ndim == 2:
        poses = poses[None]
    if poses.ndim != 3 or poses.shape[1:] != (4, 4):
        raise RenderError(f"poses must be (N, 4, 4), got {poses.shape}")
    if len(poses) == 0:
        raise RenderError("empty pose array")
    if not np.isfinite(poses).all():
        raise RenderError("poses contain NaN or Inf")
    rot = poses[:, :3, :3]
    err = np.abs(rot @ rot.transpose(0, 2, 1) - np.eye(3)).max()
    if err > 1e-6 or np.abs(poses[:, 3] - [0, 0, 0, 1]).max() > 1e-9:
        raise RenderError(f"poses are not rigid transforms (orthogonality error {err:.2e})")
    return poses


def central_gradients(height: torch.Tensor) -> torch.Tensor:
    """Central differences (one-sided at the border). ``(N, H, W)`` -> ``(N, H, W, 2)``
    with ``[..., 0] = dh/dx`` (columns) and ``[..., 1] = dh/dy`` (rows)."""
    gy, gx = torch.gradient(height, dim=(-2, -1))
    return torch.stack([gx, gy], dim=-1)


class GelRenderer:
    """Renders GelSight maps of a mesh for sensor poses in the object frame.

    Args:
        mesh: watertight object mesh in metres (open3d legacy ``TriangleMesh``).
        config: sensor geometry (``mm_per_px``, size, maximum indentation, contact rule).
        render_config: gel model parameters.
        device: where the output maps live (ray casting itself runs on the CPU).
    """

    def __init__(self, mesh: o3d.geometry.TriangleMesh, config: Config | None = None,
                 render_config: RenderConfig | None = None, device: torch.device | str = "cpu"):
        if len(mesh.triangles) == 0:
            raise RenderError("mesh has no triangles")
        self.config = config or Config()
        self.render_config = render_config or RenderConfig()
        self.device = torch.device(device)
        self.mesh = mesh
        self.scene = o3d.t.geometry.RaycastingScene()
        self.scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(mesh))
        verts = np.asarray(mesh.vertices)
        self.centre = 0.5 * (verts.min(0) + verts.max(0))
        self.radius = float(np.linalg.norm(verts - self.centre, axis=1).max())
        s = self.config.sensor
        self.pixel_xy = self.pixel_grid(s.height, s.width, s.m_per_px)

    @staticmethod
    def pixel_grid(h: int, w: int, m_per_px: float) -> np.ndarray:
        """Metric (x, y) of pixel centres on the gel plane, ``(H, W, 2)`` metres."""
        r, c = np.meshgrid(np.arange(h), np.arange(w), indexing="ij")
        return np.stack([(c - (w - 1) / 2) * m_per_px, (r - (h - 1) / 2) * m_per_px], -1)

    def _cast(self, poses: np.ndarray, pose_id: np.ndarray, xy: np.ndarray) -> np.ndarray:
        """Sensor-frame z of the first hit of rays at sensor-plane points ``xy`` ``(R, 2)``
        of poses ``poses[pose_id]`` (``pose_id`` sorted); ``+inf`` on a miss. Rays start
        behind the gel, outside the object's bounding sphere. ``(R,)`` float64."""
        z0 = np.linalg.norm(poses[:, :3, 3] - self.centre, axis=1) + self.radius + 1e-3
        rays = np.empty((len(xy), 6), dtype=np.float32)
        bounds = np.searchsorted(pose_id, np.arange(len(poses) + 1))
        for i in range(len(poses)):
            a, b = bounds[i], bounds[i + 1]
            rot = poses[i, :3, :3]
            rays[a:b, :3] = xy[a:b] @ rot[:, :2].T + (poses[i, :3, 3] - z0[i] * rot[:, 2])
            rays[a:b, 3:] = rot[:, 2]
        out = np.empty(len(xy))
        chunk = 1 << 20
        for a in range(0, len(xy), chunk):
            out[a:a + chunk] = self.scene.cast_rays(o3d.core.Tensor(rays[a:a + chunk]))["t_hit"].numpy()
        return out - z0[pose_id]

    def surface_z(self, object_T_sensor: np.ndarray, pixel_xy: np.ndarray | None = None) -> np.ndarray:
        """Sensor-frame z (metres) of the first object surface along each pixel's +z ray.

        Args:
            object_T_sensor: ``(N, 4, 4)`` sensor poses in the object frame, metres.
            pixel_xy: ``(..., 2)`` sensor-frame ray positions (metres); default: all pixels.

        Returns:
            ``(N, ...)`` float64; ``+inf`` where the ray misses the object.
        """
        poses = check_poses(object_T_sensor)
        xy = self.pixel_xy if pixel_xy is None else np.asarray(pixel_xy, dtype=np.float64)
        grid_shape = xy.shape[:-1]
        xy = xy.reshape(-1, 2)
        pose_id = np.repeat(np.arange(len(poses)), len(xy))
        z = self._cast(poses, pose_id, np.tile(xy, (len(poses), 1)))
        return z.reshape(len(poses), *grid_shape)

    def indentation_z(self, object_T_sensor: np.ndarray) -> np.ndarray:
        """:meth:`surface_z` for all pixels, but only where the object can reach the gel.

        A first pass on every ``cull_stride``-th pixel finds the cells whose surface comes
        within ``cull_margin_mm`` of the gel plane; only pixels of those cells and their
        neighbours are cast at full resolution, the rest are ``+inf`` (no indentation).
        ``(N, 4, 4)`` -> ``(N, H, W)`` metres.
        """
        poses = check_poses(object_T_sensor)
        rc = self.render_config
        k = rc.cull_stride
        if k <= 1:
            return self.surface_z(poses)
        h, w = self.pixel_xy.shape[:2]
        hc, wc = -(-h // k), -(-w // k)
        # coarse samples at the cell centres (clipped into the image)
        rows = np.minimum(np.arange(hc) * k + k // 2, h - 1)
        cols = np.minimum(np.arange(wc) * k + k // 2, w - 1)
        coarse = self.surface_z(poses, self.pixel_xy[rows][:, cols])
        near = torch.from_numpy(coarse < rc.cull_margin_mm * 1e-3)
        near = dilate(near, 3).numpy()
        full = np.repeat(np.repeat(near, k, axis=1), k, axis=2)[:, :h, :w]
        out = np.full((len(poses), h, w), np.inf)
        pid, r, c = np.nonzero(full)
        if len(pid):
            out[pid, r, c] = self._cast(poses, pid, self.pixel_xy[r, c])
        return out

    def render(self, object_T_sensor: np.ndarray) -> GelMaps:
        """Height, gradients and contact for ``(N, 4, 4)`` poses ``object_T_sensor``
        (sensor pose in the object frame, metres). See :class:`GelMaps`."""
        s = self.config.sensor
        z = self.indentation_z(object_T_sensor)
        raw = np.clip(np.minimum(z, 0.0), -s.max_indentation_mm * 1e-3, 0.0) / s.m_per_px
        height = self.smooth(torch.as_tensor(raw, dtype=torch.float32, device=self.device))
        contact_px = self.render_config.contact_depth_mm / s.mm_per_px
        contact = erode(height < -contact_px, max(s.height // 48, 1), border_is_contact=False)
        in_contact = contact.reshape(len(contact), -1).sum(1) >= self.config.min_contact_px
        return GelMaps(height=height, gradients=central_gradients(height), contact=contact, in_contact=in_contact)

    def smooth(self, height: torch.Tensor) -> torch.Tensor:
        """Elastomer low-pass of ``(N, H, W)`` heights (separable Gaussian, replicated border)."""
        sigma = self.render_config.elastomer_sigma_mm / self.config.sensor.mm_per_px
        if sigma <= 0:
            return height
        r = int(np.ceil(3 * sigma))
        k = torch.exp(-0.5 * (torch.arange(-r, r + 1, dtype=height.dtype, device=height.device) / sigma) ** 2)
        k = k / k.sum()
        x = F.pad(height[:, None], (r, r, r, r), mode="replicate")
        x = F.conv2d(F.conv2d(x, k.view(1, 1, 1, -1)), k.view(1, 1, -1, 1))
        return x[:, 0]
