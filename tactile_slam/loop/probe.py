"""Probes: a predicted second detection for a loop that waits between two groups
(``loop.probes``, off by default).

A loop between groups ``H`` and ``G`` (reference ``a`` in ``H``, query ``b`` in ``G``) implies
the transform ``H_T_G`` between their start frames, and with it a predicted pose in ``H`` for
every other keyframe of ``G``. A short session after contact loss seldom gives the second
detection the gate asks for (:class:`~tactile_slam.loop.consistency.LoopGate`): its other
keyframes came before the loop was found, or SIFT finds too few keypoints on their overlap.
A probe takes the pair ``(x in H, y in G)`` whose contact footprints overlap most under
``H_T_G`` (:func:`best_pair`) and verifies it with NormalFlow from the predicted pose (loop
CCS/SCR checks; the smaller contact is the reference). If the loop is false, ``y`` lands on
the wrong part of ``H``'s surface and the verification fails; if it is true, the probe is a
loop of another query keyframe, and the gate weighs it like one.

A verification that would pass wherever it starts is no evidence, so the pair is also
verified, in the same batch, from the alternatives of
:func:`~tactile_slam.loop.ambiguity.starts`, near ones included; the probe takes the best
nearby alignment (:func:`~tactile_slam.loop.ambiguity.best`) and counts only if no other
start verifies at a different pose (:func:`~tactile_slam.loop.ambiguity.elsewhere`). With
probes on, loops between groups also take their best nearby alignment before they predict
anything, so a loop one rib off does not send probes one rib off. That removes most
confirmations on straight growth lines and ribs, not all (6000-frame simulated scans,
docs/loops.md: the lime's largest group 56 -> 87 of 234 keyframes with no false loop, the
seed's 418 -> 433 with two loops 1.02 and 1.12 deg off, the shell's false loops 1 -> 3).
Hence off by default. Keyframes whose texture matches another part of
itself (``Loop.repetitive``) are not probed, as their loops are not merged
(``loop.trust_repetitive``).
"""

from __future__ import annotations

import math

import torch


def disc_overlap(d: torch.Tensor, r1: torch.Tensor, r2: torch.Tensor) -> torch.Tensor:
    """Intersection area of two discs at centre distance ``d`` with radii ``r1``, ``r2``,
    as a fraction of the smaller disc's area (1 when one lies inside the other, 0 when they
    are apart). All arguments broadcast; returns float64 in [0, 1]."""
    d, r1, r2 = (torch.as_tensor(v, dtype=torch.float64) for v in (d, r1, r2))
    d, r1, r2 = torch.broadcast_tensors(d, r1, r2)
    small, big = torch.minimum(r1, r2), torch.maximum(r1, r2)
    safe_d = d.clamp_min(1e-12)
    a1 = torch.arccos(((d**2 + small**2 - big**2) / (2 * safe_d * small.clamp_min(1e-12))).clamp(-1, 1))
    a2 = torch.arccos(((d**2 + big**2 - small**2) / (2 * safe_d * big.clamp_min(1e-12))).clamp(-1, 1))
    lens = (small**2 * (a1 - torch.sin(2 * a1) / 2) + big**2 * (a2 - torch.sin(2 * a2) / 2))
    frac = lens / (math.pi * small**2).clamp_min(1e-30)
    frac = torch.where(d <= big - small, torch.ones_like(frac), frac)
    return torch.where(d >= big + small, torch.zeros_like(frac), frac).clamp(0.0, 1.0)


def best_pair(H_T_G: torch.Tensor, start_T_x: torch.Tensor, centres_x: torch.Tensor, radii_x: torch.Tensor,
              start_T_y: torch.Tensor, centres_y: torch.Tensor, radii_y: torch.Tensor,
              allowed: torch.Tensor) -> tuple[int, int] | None:
    """The allowed pair of keyframes ``x`` (group ``H``) and ``y`` (group ``G``) whose contact
    footprints overlap most when ``G`` is placed in ``H`` by ``H_T_G``.

    A footprint is a disc (contact centre, radius) in the sensor plane; the overlap is the
    discs' intersection as a fraction of the smaller one (:func:`disc_overlap`). Only pairs
    that overlap at all and whose sensors face the same way are considered; ties go to the
    closer centres.

    Args:
        H_T_G: ``(4, 4)`` float64, ``G``'s start frame in ``H``'s (metres).
        start_T_x: ``(X, 4, 4)`` float64 poses of ``H``'s keyframes in ``H``'s start frame.
        centres_x: ``(X, 3)`` contact centres in each keyframe's sensor frame (metres).
        radii_x: ``(X,)`` footprint radii (metres).
        start_T_y: ``(Y, 4, 4)``, ``centres_y`` ``(Y, 3)``, ``radii_y`` ``(Y,)``: the same for ``G``.
        allowed: ``(X, Y)`` bool, pairs that may be probed.

    Returns:
        ``(i, j)``: indices into the ``x`` and ``y`` rows; None when no allowed pair overlaps.
    """
    X, Y = start_T_x.shape[0], start_T_y.shape[0]
    if H_T_G.shape != (4, 4) or start_T_x.shape != (X, 4, 4) or start_T_y.shape != (Y, 4, 4):
        raise ValueError(f"need (4, 4), (X, 4, 4) and (Y, 4, 4) poses, got {tuple(H_T_G.shape)}, "
                         f"{tuple(start_T_x.shape)} and {tuple(start_T_y.shape)}")
    if centres_x.shape != (X, 3) or centres_y.shape != (Y, 3) or radii_x.shape != (X,) or radii_y.shape != (Y,):
        raise ValueError("footprint centres must be (X, 3) / (Y, 3) and radii (X,) / (Y,)")
    if allowed.shape != (X, Y):
        raise ValueError(f"allowed must be ({X}, {Y}), got {tuple(allowed.shape)}")
    if X == 0 or Y == 0:
        return None
    H_T_y = H_T_G.double() @ start_T_y.double()
    cx = torch.einsum("xij,xj->xi", start_T_x[:, :3, :3].double(), centres_x.double()) + start_T_x[:, :3, 3].double()
    cy = torch.einsum("yij,yj->yi", H_T_y[:, :3, :3], centres_y.double()) + H_T_y[:, :3, 3]
    d = torch.cdist(cx, cy)
    overlap = disc_overlap(d, radii_x.double()[:, None], radii_y.double()[None, :])
    facing = start_T_x[:, :3, 2].double() @ H_T_y[:, :3, 2].T > 0.0
    ok = allowed & facing & (overlap > 0.0) & torch.isfinite(d)
    if not bool(ok.any()):
        return None
    score = torch.where(ok, overlap, torch.full_like(overlap, -1.0))
    best = ok & (score == score.max())
    flat = int(torch.where(best, d, torch.full_like(d, torch.inf)).argmin())
    return divmod(flat, Y)
