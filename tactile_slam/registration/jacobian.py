"""NormalFlow's per-sample Jacobian with respect to the twist (method.md section 4.3).

The twist is ``delta = (wx, wy, wz, tx, ty)`` (rad, m) and the incremental transform
is ``dT = [Rz(wz) Ry(wy) Rx(wx) | (tx, ty, 0)]``. In the inverse-compositional form the
Jacobian lives on the reference side: it is the derivative at ``delta = 0`` of

    r_k(delta) = R(delta)^T (n_k + D_k (proj(dT P_k) - proj(P_k)))

where ``P_k`` is the sample's metric point, ``n_k`` its normal and ``D_k`` (3, 2) the
normal map's derivative per metre (5x5 Sobel). :func:`jacobian_autograd` differentiates
that function with ``torch.func``; :func:`jacobian_analytic` is the closed form
``J = D Jw + [[n]x | 0]``. The two agree to rounding (tested).
"""

from __future__ import annotations

import cv2
import numpy as np
import torch
from torch.func import jacrev, vmap

_SOBEL_SMOOTH = (1.0, 4.0, 6.0, 4.0, 1.0)
_SOBEL_DERIV = (-1.0, -2.0, 0.0, 2.0, 1.0)
_SOBEL_GAIN = 128.0  # response of the 5x5 Sobel to a unit ramp


# Entries of Rx, Ry, Rz as indices into [cos(w) (3), sin(w) (3), -sin(w) (3), 0, 1].
_EULER_INDEX = [
    10, 9, 9, 9, 0, 6, 9, 3, 0,  # Rx
    1, 9, 4, 9, 10, 9, 7, 9, 1,  # Ry
    2, 8, 9, 5, 2, 9, 9, 9, 10,  # Rz
]


def euler_to_matrix(angles):
    """``R = Rz(wz) Ry(wy) Rx(wx)`` (scipy's extrinsic "xyz"); differentiable for
    tensors, and the same for numpy arrays (the host-side pose updates).

    ``(B, 3)`` angles in rad -> ``(B, 3, 3)``.
    """
    xp = np if isinstance(angles, np.ndarray) else torch
    s = xp.sin(angles)
    zero = angles[:, :1] * 0
    table = xp.concatenate([xp.cos(angles), s, -s, zero, zero + 1], 1)
    m = table[:, _EULER_INDEX].reshape(-1, 3, 3, 3)
    return m[:, 2] @ m[:, 1] @ m[:, 0]


def sobel_at(maps: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
    """5x5 Sobel derivatives of a multi-channel map at selected pixels, per pixel, with
    reflect-101 borders (OpenCV's default).

    On the CPU, OpenCV filters the bounding box of the pixels (grown by the kernel's
    radius where the image allows, so every 5x5 window and every reflected border is the
    full image's) and the pixels are looked up: a 5x5 patch gather per pixel costs more
    than the filter. Elsewhere :func:`sobel_at_patches`. Both give the same values
    (tested).

    Args:
        maps: ``(B, H, W, C)``.
        idx: ``(B, K)`` int64 row-major pixel indices.

    Returns:
        ``(B, K, C, 2)``: derivative along x (columns) and along y (rows), per pixel.
    """
    if maps.device.type != "cpu":
        return sobel_at_patches(maps, idx)
    b, h, w, ch = maps.shape
    arr = maps.detach().contiguous().numpy()
    depth = cv2.CV_64F if arr.dtype == np.float64 else cv2.CV_32F
    rows, cols = np.divmod(idx.numpy(), w)
    out = []
    for i in range(b):
        r0, r1 = max(int(rows[i].min()) - 2, 0), min(int(rows[i].max()) + 3, h)
        c0, c1 = max(int(cols[i].min()) - 2, 0), min(int(cols[i].max()) + 3, w)
        img = arr[i, r0:r1, c0:c1]
        img = img if ch > 1 else img[..., 0]
        at = (rows[i] - r0) * (c1 - c0) + cols[i] - c0
        d = [cv2.Sobel(img, depth, dx, 1 - dx, ksize=5, scale=1.0 / _SOBEL_GAIN).reshape(-1, ch)[at]
             for dx in (1, 0)]
        out.append(np.stack(d, axis=-1))
    return torch.from_numpy(np.stack(out)).to(maps.dtype)


def sobel_at_patches(maps: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
    """5x5 Sobel derivatives of a multi-channel map at selected pixels, from their 5x5 patches
    (any device; :func:`sobel_at` uses it off the CPU).

    Border pixels use reflect-101 (OpenCV's default), so the values equal a full-image
    Sobel followed by a lookup.

    Args:
        maps: ``(B, H, W, C)``.
        idx: ``(B, K)`` int64 row-major pixel indices.

    Returns:
        ``(B, K, C, 2)``: derivative along x (columns) and along y (rows), per pixel.
    """
    b, h, w, ch = maps.shape
    dev = maps.device
    off = torch.arange(-2, 3, device=dev)
    r = (idx // w)[..., None, None] + off[:, None]  # (B, K, 5, 1): row offsets
    c = (idx % w)[..., None, None] + off[None, :]  # (B, K, 1, 5): column offsets
    r = (h - 1) - ((h - 1) - r.abs()).abs()  # reflect-101 (valid for 2 <= h)
    c = (w - 1) - ((w - 1) - c.abs()).abs()
    flat = (r * w + c).reshape(b, -1) + torch.arange(b, device=dev)[:, None] * (h * w)  # (B, K*25)
    patch = maps.reshape(b * h * w, ch).index_select(0, flat.reshape(-1))  # one row gather, row offset major
    smooth = torch.tensor(_SOBEL_SMOOTH, dtype=maps.dtype, device=dev)
    deriv = torch.tensor(_SOBEL_DERIV, dtype=maps.dtype, device=dev)
    kx = torch.outer(smooth, deriv).reshape(25) / _SOBEL_GAIN  # rows smooth, columns differentiate
    ky = torch.outer(deriv, smooth).reshape(25) / _SOBEL_GAIN
    # one GEMM: a (C*2, 25*C) block kernel times the (25*C, B*K) patches
    eye = torch.eye(ch, dtype=maps.dtype, device=dev)
    block = torch.stack([kx, ky], dim=1)[:, None, None, :] * eye[None, :, :, None]  # (25, C, C, 2)
    out = block.reshape(25 * ch, ch * 2).T @ patch.reshape(-1, 25 * ch).T
    return out.T.reshape(b, idx.shape[1], ch, 2)


def jacobian_analytic(points_t: torch.Tensor, normals_t: torch.Tensor, dn_t: torch.Tensor) -> torch.Tensor:
    """Closed-form ``J_k = D_k Jw_k + [[n_k]x | 0]``, channels first (the layout the
    Gauss-Newton products read, so no transpose is needed).

    Args:
        points_t: ``(B, 3, K)`` sample points P_k in metres (reference sensor frame).
        normals_t: ``(B, 3, K)`` reference normals n_k.
        dn_t: ``(B, 3, 2, K)`` normal-map derivatives per metre (channel, x/y, sample).

    Returns:
        ``(B, 5, 3, K)``: d residual channel / d (wx, wy, wz, tx, ty), per sample.
    """
    px, py, pz = (x.unsqueeze(1) for x in points_t.unbind(1))  # (B, 1, K)
    nx, ny, nz = normals_t.unbind(1)
    dx, dy = dn_t.unbind(2)  # (B, 3, K)
    zero = torch.zeros_like(nx)
    # D Jw with Jw rows x: [0, Pz, -Py, 1, 0] and y: [-Pz, 0, Px, 0, 1], plus the
    # columns of [n]x = [[0, -nz, ny], [nz, 0, -nx], [-ny, nx, 0]]
    j0 = torch.stack([zero, nz, -ny], 1) - dy * pz
    j1 = torch.stack([-nz, zero, nx], 1) + dx * pz
    j2 = torch.stack([ny, -nx, zero], 1) + dy * px - dx * py
    return torch.stack([j0, j1, j2, dx, dy], 1)


def _linearised_residual(delta: torch.Tensor, point: torch.Tensor, normal: torch.Tensor, dn: torch.Tensor):
    """``R(delta)^T (n + D (proj(dT P) - proj(P)))`` for one sample; ``delta`` (5,)."""
    rot = euler_to_matrix(delta[:3].unsqueeze(0))[0]
    moved = rot @ point + torch.cat([delta[3:], delta[:1] * 0])
    return rot.transpose(0, 1) @ (normal + dn @ (moved[:2] - point[:2]))


def jacobian_autograd(points_t: torch.Tensor, normals_t: torch.Tensor, dn_t: torch.Tensor) -> torch.Tensor:
    """Same as :func:`jacobian_analytic`, by reverse-mode autograd (``torch.func``),
    vectorised over samples. Shapes as there."""
    b, _, k = points_t.shape
    p = points_t.mT.reshape(-1, 3)
    n = normals_t.mT.reshape(-1, 3)
    d = dn_t.permute(0, 3, 1, 2).reshape(-1, 3, 2)
    zero = torch.zeros(5, dtype=points_t.dtype, device=points_t.device)
    jac = vmap(jacrev(_linearised_residual), in_dims=(None, 0, 0, 0))(zero, p, n, d)  # (B K, 3, 5)
    return jac.view(b, k, 3, 5).permute(0, 3, 2, 1)
