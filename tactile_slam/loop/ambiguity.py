"""Is a verified alignment the only one? NormalFlow from alternative starts.

A loop's NormalFlow verification (CCS/SCR) says the two keyframes' surfaces agree at the
measured pose; it does not say they agree *only* there. On a flat face, straight growth
lines or a smooth dome they also agree half a contact away or half a turn round, and
NormalFlow started there stays there and verifies. Such a pair is no evidence of *where*
the two touches were, so it cannot join two groups (it still serves within a group, where
the estimate predicts the loop; :class:`~tactile_slam.loop.consistency.LoopGate`).

:func:`starts` gives the alternatives: the measured (or predicted) pose shifted by half the
reference contact's radius along +-x and +-y, and turned by a quarter, a half and three
quarters about its contact centre. The pair is verified from all of them in one batch with
the loop's checks, and :func:`elsewhere` says whether any alternative verified at a pose
beyond the gate's base tolerance from the first. Used by the back end for every loop
between two groups (``loop.check_ambiguity``) and by probes (:mod:`tactile_slam.loop.probe`).
"""

from __future__ import annotations

import math

import torch

from tactile_slam.loop.consistency import DriftModel, consistent


def starts(q_T_c: torch.Tensor, centre: torch.Tensor, radius_m: float) -> torch.Tensor:
    """A pose and the alternatives that must not verify elsewhere.

    Args:
        q_T_c: ``(4, 4)`` float64 pose of keyframe ``c`` in keyframe ``q`` (metres), measured
            or predicted; ``q`` is NormalFlow's reference.
        centre: ``(3,)`` ``q``'s contact centre in its sensor frame (metres).
        radius_m: ``q``'s footprint radius (metres).

    Returns:
        ``(8, 4, 4)`` float64: ``q_T_c``; then ``q_T_c`` shifted by half the radius along
        +x, -x, +y, -y of ``q``'s sensor frame; then turned by a quarter, a half and three
        quarters about the sensor z axis through ``centre``.
    """
    if q_T_c.shape != (4, 4) or centre.shape != (3,):
        raise ValueError(f"need a (4, 4) pose and a (3,) centre, got {tuple(q_T_c.shape)} and {tuple(centre.shape)}")
    if not (math.isfinite(radius_m) and radius_m > 0.0):
        raise ValueError(f"radius must be finite and positive, got {radius_m}")
    moves = torch.eye(4, dtype=torch.float64).repeat(7, 1, 1)
    h = radius_m / 2.0
    moves[:4, :2, 3] = torch.tensor([[h, 0.0], [-h, 0.0], [0.0, h], [0.0, -h]], dtype=torch.float64)
    a = torch.deg2rad(torch.tensor([90.0, 180.0, 270.0], dtype=torch.float64))
    R = moves[4:, :3, :3]
    R[:, 0, 0], R[:, 0, 1], R[:, 1, 0], R[:, 1, 1] = a.cos(), -a.sin(), a.sin(), a.cos()
    c = centre.double()
    moves[4:, :3, 3] = c - R @ c  # rotation about c: x -> R (x - c) + c
    return torch.cat([q_T_c.double()[None], moves @ q_T_c.double()])


def elsewhere(q_T_c: torch.Tensor, ok: torch.Tensor, model: DriftModel) -> torch.Tensor:
    """Whether an alternative start verified somewhere else.

    Args:
        q_T_c: ``(B, S, 4, 4)`` float64 results of NormalFlow from the ``S`` starts of each of
            ``B`` pairs (the first start is the pair's own pose).
        ok: ``(B, S)`` bool, which results passed the loop checks.
        model: the drift tolerance; its base (zero path) decides "somewhere else".

    Returns:
        ``(B,)`` bool: some start other than the first verified at a pose beyond the base
        tolerance from the first start's result.
    """
    B, S = ok.shape
    if q_T_c.shape != (B, S, 4, 4):
        raise ValueError(f"need (B, S, 4, 4) poses for (B, S) = {tuple(ok.shape)} checks, got {tuple(q_T_c.shape)}")
    T = q_T_c.double().reshape(B * S, 4, 4)
    first = q_T_c[:, :1].double().expand(B, S, 4, 4).reshape(B * S, 4, 4)
    same = consistent(first, T, torch.zeros(B * S, dtype=torch.float64), model).reshape(B, S)
    return (ok.bool() & ~same)[:, 1:].any(dim=1)
