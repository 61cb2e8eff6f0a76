"""Is a verified alignment the only one? NormalFlow from alternative starts.

A loop's NormalFlow verification (CCS/SCR) says the two keyframes' surfaces agree at the
measured pose; it does not say they agree *only* there. On a flat face, straight growth
lines or a smooth dome they also agree half a contact away or half a turn round, and
NormalFlow started there stays there and verifies. Such a pair is no evidence of *where*
the two touches were, so it cannot join two groups (it still serves within a group, where
the estimate predicts the loop; :class:`~tactile_slam.loop.consistency.LoopGate`).

:func:`starts` gives the alternatives: the measured (or predicted) pose shifted by half the
reference contact's radius along +-x and +-y, turned by a quarter, a half and three quarters
about its contact centre, and (for probes) shifted by the gate's base translation tolerance
along +-x and +-y. The pair is verified from all of them in one batch with the loop's checks.

The near shifts look for a better alignment the gate could not tell apart: on ribs or
grooves a fraction of a millimetre apart NormalFlow started one period off stays there
and verifies (CCS 0.92-0.98 on the simulated shell, 0.997 one rib over, at the truth).
:func:`best` picks, among the first start and the near ones, the verified result with the
highest CCS; the loop takes that pose. :func:`elsewhere` then says whether any other start
verified at a pose beyond the gate's base tolerance from it.

Used by the back end for every loop between two groups (``loop.check_ambiguity``; with
``loop.best_nearby`` or probes on, the near starts first choose the loop's pose, and do not
count as elsewhere), for loops within a group that differ from the estimate's prediction
(``loop.best_nearby``, likewise), and by probes (:mod:`tactile_slam.loop.probe`; every start
counts: a probe's prediction may itself be a period off, and only a unique alignment
confirms it).
"""

from __future__ import annotations

import math

import torch

from tactile_slam.loop.consistency import DriftModel, consistent
from tactile_slam.posegraph import se3


NEAR = slice(8, 12)
"""Where :func:`starts` puts the shifts by the base tolerance (:func:`best` looks there)."""


def starts(q_T_c: torch.Tensor, centre: torch.Tensor, radius_m: float, near_m: float | None = None) -> torch.Tensor:
    """A pose and the alternatives that must not verify elsewhere.

    Args:
        q_T_c: ``(4, 4)`` float64 pose of keyframe ``c`` in keyframe ``q`` (metres), measured
            or predicted; ``q`` is NormalFlow's reference.
        centre: ``(3,)`` ``q``'s contact centre in its sensor frame (metres).
        radius_m: ``q``'s footprint radius (metres).
        near_m: the near shift (metres): the gate's base translation tolerance; ``None``
            for no near starts.

    Returns:
        ``(12, 4, 4)`` float64 (``(8, 4, 4)`` without near starts): ``q_T_c``; then
        ``q_T_c`` shifted by half the radius along +x, -x, +y, -y of ``q``'s sensor frame;
        then turned by a quarter, a half and three quarters about the sensor z axis through
        ``centre``; then (:data:`NEAR`) shifted by ``near_m`` along +x, -x, +y, -y.
    """
    if q_T_c.shape != (4, 4) or centre.shape != (3,):
        raise ValueError(f"need a (4, 4) pose and a (3,) centre, got {tuple(q_T_c.shape)} and {tuple(centre.shape)}")
    if not (math.isfinite(radius_m) and radius_m > 0.0):
        raise ValueError(f"radius must be finite and positive, got {radius_m}")
    if near_m is not None and not (math.isfinite(near_m) and near_m > 0.0):
        raise ValueError(f"near shift must be finite and positive, got {near_m}")
    turns = torch.eye(4, dtype=torch.float64).repeat(3, 1, 1)
    a = torch.deg2rad(torch.tensor([90.0, 180.0, 270.0], dtype=torch.float64))
    R = turns[:, :3, :3]
    R[:, 0, 0], R[:, 0, 1], R[:, 1, 0], R[:, 1, 1] = a.cos(), -a.sin(), a.sin(), a.cos()
    c = centre.double()
    turns[:, :3, 3] = c - R @ c  # rotation about c: x -> R (x - c) + c
    moves = [se3.shifts_xy(radius_m / 2.0), turns] + ([] if near_m is None else [se3.shifts_xy(near_m)])
    return torch.cat([q_T_c.double()[None], torch.cat(moves) @ q_T_c.double()])


def best(ok: torch.Tensor, ccs: torch.Tensor) -> torch.Tensor:
    """Which of the competing starts, the first and the :data:`NEAR` ones of :func:`starts`
    (``S`` = 12), gives the verified result with the highest CCS.

    Args:
        ok: ``(B, S)`` bool, which results passed the loop checks.
        ccs: ``(B, S)`` their CCS.

    Returns:
        ``(B,)`` int64 start index; the first where none of them verified (and where the
        first ties with the best).
    """
    if ok.shape != ccs.shape or ok.dim() != 2 or ok.shape[1] < NEAR.stop:
        raise ValueError(f"need (B, S > {NEAR.stop - 1}) checks and CCS, got {tuple(ok.shape)} and {tuple(ccs.shape)}")
    idx = torch.tensor([0, *range(NEAR.start, NEAR.stop)], device=ok.device)
    score = torch.where(ok[:, idx], ccs[:, idx].double().nan_to_num(-math.inf), -math.inf)
    return idx[score.argmax(dim=1)]  # argmax takes the first of equal scores: the first start


def elsewhere(q_T_c: torch.Tensor, ok: torch.Tensor, model: DriftModel, at: torch.Tensor | None = None,
              near: bool = True) -> torch.Tensor:
    """Whether an alternative start verified somewhere else.

    Args:
        q_T_c: ``(B, S, 4, 4)`` float64 results of NormalFlow from the ``S`` starts of each of
            ``B`` pairs (the first start is the pair's own pose).
        ok: ``(B, S)`` bool, which results passed the loop checks.
        model: the drift tolerance; its base (zero path) decides "somewhere else".
        at: ``(B,)`` int64 the result the others are compared with (:func:`best`); the
            first start's if ``None``.
        near: whether the :data:`NEAR` starts count (when ``S`` reaches them). On ribs a
            near start also lands two periods over and verifies there: evidence of a
            periodic surface that a loop found by retrieval survives (its features chose
            the place) but a probe, which only confirms a prediction, does not.

    Returns:
        ``(B,)`` bool: some other start verified at a pose beyond the base tolerance from
        result ``at``.
    """
    B, S = ok.shape
    if q_T_c.shape != (B, S, 4, 4):
        raise ValueError(f"need (B, S, 4, 4) poses for (B, S) = {tuple(ok.shape)} checks, got {tuple(q_T_c.shape)}")
    at = torch.zeros(B, dtype=torch.long) if at is None else at.long().cpu()
    T = q_T_c.double().reshape(B * S, 4, 4)
    chosen = q_T_c[torch.arange(B), at].double()[:, None].expand(B, S, 4, 4).reshape(B * S, 4, 4)
    same = consistent(chosen, T, torch.zeros(B * S, dtype=torch.float64), model).reshape(B, S)
    counted = ok.bool().cpu().clone()
    if not near and S >= NEAR.stop:
        chosen_ok = counted[torch.arange(B), at]
        counted[:, NEAR] = False
        counted[torch.arange(B), at] = chosen_ok
    return (counted & ~same).any(dim=1)
