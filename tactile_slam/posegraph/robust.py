"""Robust kernels and the GNC-TLS weight rule for loop factors (method.md sections 6.4, 7.2).

All functions take squared whitened residual norms ``s = |e / sigma|^2`` ``(L,)`` and return
tensors of the same shape. ``k2`` is the kernel's squared scale in whitened units (the inlier
threshold; 16.81 is the 0.99 quantile of chi-square with 6 degrees of freedom).
"""

from __future__ import annotations

import torch

KERNELS = ("none", "huber", "cauchy")


def kernel_cost(kind: str, s: torch.Tensor, k2: float) -> torch.Tensor:
    """rho(s): ``s`` (none), Huber ``2k|e| - k^2`` past ``k``, Cauchy ``k^2 log(1 + s/k^2)``."""
    if kind == "none":
        return s
    if kind == "huber":
        k = k2 ** 0.5
        return torch.where(s <= k2, s, 2 * k * s.sqrt() - k2)
    if kind == "cauchy":
        return k2 * torch.log1p(s / k2)
    raise ValueError(f"robust kernel must be one of {KERNELS}, got {kind!r}")


def kernel_weight(kind: str, s: torch.Tensor, k2: float) -> torch.Tensor:
    """IRLS weights ``rho'(s)`` in (0, 1]."""
    if kind == "none":
        return torch.ones_like(s)
    if kind == "huber":
        return torch.where(s <= k2, torch.ones_like(s), (k2 / s.clamp_min(1e-300)).sqrt())
    if kind == "cauchy":
        return 1.0 / (1.0 + s / k2)
    raise ValueError(f"robust kernel must be one of {KERNELS}, got {kind!r}")


def gnc_initial_mu(s: torch.Tensor, c2: float) -> float:
    """First GNC control parameter for TLS (Yang et al. 2020): ``c^2 / (2 max(s) - c^2)``.

    Returns ``inf`` when every residual is already below ``c2`` (nothing to reject).
    """
    smax = float(s.max()) if s.numel() else 0.0
    return float("inf") if 2 * smax <= c2 else c2 / (2 * smax - c2)


def gnc_tls_weights(s: torch.Tensor, mu: float, c2: float) -> torch.Tensor:
    """Closed-form GNC-TLS weights in [0, 1] for control parameter ``mu`` and threshold ``c2``.

    1 below ``mu/(mu+1) c2``, 0 above ``(mu+1)/mu c2``, ``c sqrt(mu(mu+1)/s) - mu`` between.
    """
    if mu == float("inf"):
        return (s <= c2).to(s.dtype)
    lo, hi = mu / (mu + 1) * c2, (mu + 1) / mu * c2
    mid = (c2 ** 0.5) * torch.sqrt(mu * (mu + 1) / s.clamp_min(1e-300)) - mu
    return torch.where(s <= lo, torch.ones_like(s), torch.where(s >= hi, torch.zeros_like(s), mid))
