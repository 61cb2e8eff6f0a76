"""Test oracle: frame pairs with known tar_T_ref, built at the height/gradient level.

An object's lower surface is an analytic height field ``z = f(x, y)`` (metres) in the
reference sensor frame: a dome plus a texture of sinusoids and Gaussian bumps, capped
at ``CAP_M`` (a legitimate rigid object). The gel takes ``h = min(0, z)``. The target
sees the same object moved by ``tar_T_ref``: each target pixel is traced back to the
object point that lands on it (a contracting fixed-point iteration on the exact rigid
map), so the target heights are exact, not warped images. Gradients come from central
differences of the pixel heights, the contact is ``h < -margin`` eroded 5x5, and the
frames are built with ``FrameBuilder.from_gradients``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields, replace

import torch

from tactile_slam.config import Config
from tactile_slam.geometry.frame import Frame, FrameBuilder
from tactile_slam.geometry.morphology import erode

H, W = 240, 320
S = 0.0634e-3  # metres per pixel
CAP_M = 3e-3


@dataclass
class Surface:
    """Object surface parameters (metres)."""

    depth: float = 1.0e-3
    dome_radius: float = 10e-3
    dome_scale_y: float = 1.0  # != 1 for an elongated (ellipsoidal) dome
    flat: bool = False  # a flat face pressed into the gel (no texture, no dome)
    waves: list[tuple[float, float, float, float]] = field(default_factory=list)  # amp, wavelength, angle, phase
    bumps: list[tuple[float, float, float, float]] = field(default_factory=list)  # amp, sigma, x, y

    def __call__(self, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        if self.flat:
            return torch.full_like(x, -self.depth)
        z = -self.depth + (x**2 + (y / self.dome_scale_y) ** 2) / (2 * self.dome_radius)
        for amp, lam, ang, ph in self.waves:
            z = z + amp * torch.sin(2 * math.pi * (x * math.cos(ang) + y * math.sin(ang)) / lam + ph)
        for amp, sig, bx, by in self.bumps:
            z = z + amp * torch.exp(-((x - bx) ** 2 + (y - by) ** 2) / (2 * sig**2))
        return z.clamp(max=CAP_M)


def textured(seed: int = 0, amp: float = 40e-6) -> Surface:
    """A dome with random waves and bumps (texture scale 0.6-2 mm)."""
    g = torch.Generator().manual_seed(seed)
    u = lambda lo, hi: float(lo + (hi - lo) * torch.rand((), generator=g, dtype=torch.float64))  # noqa: E731
    waves = [(amp * u(0.5, 1.0), u(0.8e-3, 2e-3), u(0, math.pi), u(0, 2 * math.pi)) for _ in range(4)]
    bumps = [(u(-1, 1) * 2.5 * amp, u(0.2e-3, 0.5e-3), u(-3e-3, 3e-3), u(-3e-3, 3e-3)) for _ in range(8)]
    return Surface(waves=waves, bumps=bumps)


def bumpy(seed: int = 0, n: int = 14, amp: float = 60e-6) -> Surface:
    """A dome with ``n`` random Gaussian bumps and dents (sigma 0.25-0.8 mm)."""
    g = torch.Generator().manual_seed(seed)
    u = lambda lo, hi: float(lo + (hi - lo) * torch.rand((), generator=g, dtype=torch.float64))  # noqa: E731
    bumps = [(u(-1, 1) * amp, u(0.25e-3, 0.8e-3), u(-3.5e-3, 3.5e-3), u(-3.5e-3, 3.5e-3)) for _ in range(n)]
    return Surface(bumps=bumps)


def speckled(seed: int = 0, n: int = 120, amp: float = 60e-6) -> Surface:
    """A dome with ``n`` small random bumps and dents (sigma 0.15-0.4 mm, within 5 mm of the
    centre): no waves, so no turn or shift maps the texture onto itself."""
    g = torch.Generator().manual_seed(seed)
    u = lambda lo, hi: float(lo + (hi - lo) * torch.rand((), generator=g, dtype=torch.float64))  # noqa: E731
    bumps = [(u(-1, 1) * amp, u(0.15e-3, 0.4e-3), u(-5e-3, 5e-3), u(-5e-3, 5e-3)) for _ in range(n)]
    return Surface(bumps=bumps)


def rigid(rx_deg=0.0, ry_deg=0.0, rz_deg=0.0, tx_mm=0.0, ty_mm=0.0, tz_mm=0.0) -> torch.Tensor:
    """``(4, 4)`` float64 ``[Rz Ry Rx | t]``, angles in degrees, translation in mm."""
    ax, ay, az = (math.radians(a) for a in (rx_deg, ry_deg, rz_deg))
    f64 = torch.float64
    rx = torch.tensor([[1, 0, 0], [0, math.cos(ax), -math.sin(ax)], [0, math.sin(ax), math.cos(ax)]], dtype=f64)
    ry = torch.tensor([[math.cos(ay), 0, math.sin(ay)], [0, 1, 0], [-math.sin(ay), 0, math.cos(ay)]], dtype=f64)
    rz = torch.tensor([[math.cos(az), -math.sin(az), 0], [math.sin(az), math.cos(az), 0], [0, 0, 1]], dtype=f64)
    T = torch.eye(4, dtype=f64)
    T[:3, :3] = rz @ ry @ rx
    T[:3, 3] = torch.tensor([tx_mm, ty_mm, tz_mm], dtype=torch.float64) * 1e-3
    return T


def pixel_grid() -> tuple[torch.Tensor, torch.Tensor]:
    """Metric ``(x, y)`` of every pixel, ``(H, W)`` each (method.md section 1.2)."""
    y = (torch.arange(H, dtype=torch.float64)[:, None] - (H - 1) / 2) * S
    x = (torch.arange(W, dtype=torch.float64)[None, :] - (W - 1) / 2) * S
    return x.expand(H, W), y.expand(H, W)


def object_height(surface: Surface, T: torch.Tensor, iters: int = 40) -> torch.Tensor:
    """Height ``z`` (metres) of the object surface moved by ``T``, seen at each pixel.

    Solves ``[R q + t]_xy = (x, y)`` for the object point ``q = (x0, y0, f(x0, y0))``.
    """
    x, y = pixel_grid()
    R, t = T[:3, :3], T[:3, 3]
    a_inv = torch.linalg.inv(R[:2, :2])
    x0, y0 = x.clone(), y.clone()
    for _ in range(iters):
        z0 = surface(x0, y0)
        bx = x - t[0] - R[0, 2] * z0
        by = y - t[1] - R[1, 2] * z0
        x1 = a_inv[0, 0] * bx + a_inv[0, 1] * by
        y1 = a_inv[1, 0] * bx + a_inv[1, 1] * by
        step = float(torch.maximum((x1 - x0).abs().max(), (y1 - y0).abs().max()))
        x0, y0 = x1, y1
        if step < 1e-12:
            break
    z0 = surface(x0, y0)
    return R[2, 0] * x0 + R[2, 1] * y0 + R[2, 2] * z0 + t[2]


def frames(surface: Surface, poses: list[torch.Tensor], margin: float = 30e-6) -> Frame:
    """Frames of ``surface`` moved by each pose (``(4, 4)`` tar_T_ref; identity is the
    reference), as one float32 batch."""
    hs = torch.stack([object_height(surface, T).clamp(max=0.0) for T in poses]) / S  # px
    gy, gx = torch.gradient(hs, dim=(1, 2))
    grads = torch.stack([gx, gy], dim=-1)
    contact = erode(hs < -margin / S, 5, border_is_contact=False)
    return FrameBuilder(Config()).from_gradients(grads.float(), contact)


def pair(surface: Surface, T: torch.Tensor) -> tuple[Frame, Frame]:
    """``(ref, tar)`` frames, each ``B = 1``, with ``tar_T_ref = T``."""
    f = frames(surface, [torch.eye(4, dtype=torch.float64), T])
    return f[0], f[1]


def as_dtype(frame: Frame, dtype: torch.dtype) -> Frame:
    """The frame with its float maps cast to ``dtype``."""
    kw = {f.name: getattr(frame, f.name).to(dtype) for f in fields(frame)
          if f.name in ("gradients", "height", "normals", "curvature")}
    return replace(frame, **kw)
