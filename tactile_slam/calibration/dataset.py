"""Training samples from labelled presses: analytic sphere targets and background samples.

method.md section 2.2-2.3: inside each labelled disc shrunk by a margin (default
:func:`~tactile_slam.calibration.labels.rim_margin_px`: 4 px on the Mini) the target
angles are those of a sphere of the catalogued diameter, ``theta_x = atan2(dx, dz)``,
``theta_y = atan2(dy, dz)`` with ``dz = sqrt(R^2 - dx^2 - dy^2)``; a press whose label is
wider than the ball (``R < radius - margin``) is "too deep" and skipped. Background
pixels are zero-angle samples, 1/5 of the contact count of each split, drawn without
overlap from one seeded permutation. Presses are split by image with a seeded
permutation (first ``floor((1 - test_fraction) N)`` train).
"""

from __future__ import annotations

from collections.abc import Iterator

import math
from dataclasses import dataclass, field

import torch

from tactile_slam.calibration.catalog import CalibrationDataError, CalibrationSet, Press
from tactile_slam.calibration.labels import RIM_MARGIN_PX, PressLabel, rim_margin_px
from tactile_slam.calibration.model import pixel_features


@dataclass
class Samples:
    """Per-pixel samples: ``features`` ``(N, 5)`` float32 model input, ``angles`` ``(N, 2)``
    float32 target angles (rad), ``press`` ``(N,)`` int64 index into ``reldirs`` (-1:
    background)."""

    features: torch.Tensor
    angles: torch.Tensor
    press: torch.Tensor
    reldirs: list[str]

    def __len__(self) -> int:
        return self.features.shape[0]

    def to(self, device: torch.device | str) -> "Samples":
        return Samples(self.features.to(device), self.angles.to(device), self.press.to(device), self.reldirs)


@dataclass
class CalibrationData:
    """Train and test samples, the split (reldirs) and the presses left out, with reasons."""

    train: Samples
    test: Samples
    split: dict[str, list[str]]
    skipped: dict[str, str] = field(default_factory=dict)


def sphere_targets(
    shape: tuple[int, int], cx: float, cy: float, radius: float, ball_radius_px: float,
    margin_px: float = RIM_MARGIN_PX,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Analytic gradient angles of a ball press.

    Args:
        shape: ``(H, W)``.
        cx, cy, radius: contact circle in px (column, row, radius).
        ball_radius_px: ball radius ``R`` in px.
        margin_px: the disc used is ``||(x, y) - c|| < radius - margin_px``.

    Returns:
        ``angles`` ``(H, W, 2)`` float32 ``(theta_x, theta_y)`` in rad, zero outside the
        disc; ``mask`` ``(H, W)`` bool.

    Raises:
        ValueError: the press is too deep (``R < radius - margin_px``) or the disc is empty.
    """
    inner = radius - margin_px
    if ball_radius_px < inner:
        raise ValueError(f"press too deep: ball radius {ball_radius_px:.1f} px < label radius - margin {inner:.1f} px")
    if inner <= 0:
        raise ValueError(f"label radius {radius:.1f} px leaves no pixels after the {margin_px:g} px margin")
    h, w = shape
    ys, xs = torch.meshgrid(torch.arange(h, dtype=torch.float64), torch.arange(w, dtype=torch.float64), indexing="ij")
    dx, dy = xs - cx, ys - cy
    mask = dx**2 + dy**2 < inner**2
    dz = torch.sqrt((ball_radius_px**2 - dx**2 - dy**2).clamp_min(1e-12))
    angles = torch.stack([torch.atan2(dx, dz), torch.atan2(dy, dz)], dim=-1)
    angles = torch.where(mask[..., None], angles, torch.zeros((), dtype=torch.float64))
    return angles.float(), mask


def split_presses(reldirs: list[str], seed: int, test_fraction: float = 0.2) -> dict[str, list[str]]:
    """Seeded split by press: ``{"train": [...], "test": [...]}`` (first ``floor((1-f) N)`` of a permutation train)."""
    if not 0.0 <= test_fraction < 1.0:
        raise ValueError(f"test_fraction must be in [0, 1), got {test_fraction}")
    if not reldirs:
        raise ValueError("no presses to split")
    perm = torch.randperm(len(reldirs), generator=torch.Generator().manual_seed(seed)).tolist()
    n_train = max(1, math.floor((1.0 - test_fraction) * len(reldirs)))
    return {"train": [reldirs[i] for i in perm[:n_train]], "test": [reldirs[i] for i in perm[n_train:]]}


def split_by_diameter(calib: CalibrationSet, held_out_mm: float) -> dict[str, list[str]]:
    """Leave one ball size out: ``{"train": presses of every other diameter, "test": the
    presses of ``held_out_mm``}``, each in catalog order. Measures how a model decodes
    presses of a ball it was never trained on.

    Raises:
        ValueError: no press has that diameter, or no press has another one.
    """
    test = [p.reldir for p in calib.presses if math.isclose(p.diameter_mm, held_out_mm)]
    train = [p.reldir for p in calib.presses if not math.isclose(p.diameter_mm, held_out_mm)]
    sizes = sorted({p.diameter_mm for p in calib.presses})
    if not test:
        raise ValueError(f"no press of {held_out_mm} mm in {calib.root} (diameters {sizes})")
    if not train:
        raise ValueError(f"every press of {calib.root} is {held_out_mm} mm: nothing to train on without them")
    return {"train": train, "test": test}


def labelled_targets(
    calib: CalibrationSet, labels: dict[str, PressLabel], reldirs: list[str], mm_per_px: float,
    margin_px: float | None, skipped: dict[str, str],
) -> Iterator[tuple[str, Press, torch.Tensor, torch.Tensor]]:
    """``(reldir, press, angles (H, W, 2), mask (H, W))`` for each usable press of
    ``reldirs``; presses left out (unreliable label, too deep, disc off the image) are
    recorded in ``skipped`` with the reason. ``margin_px`` ``None``: the rim margin at
    ``mm_per_px`` (:func:`~tactile_slam.calibration.labels.rim_margin_px`).

    Raises:
        CalibrationDataError: a press has no label.
    """
    margin_px = rim_margin_px(mm_per_px) if margin_px is None else margin_px
    for reldir in reldirs:
        if reldir not in labels:
            raise CalibrationDataError(f"press {reldir} has no label")
        lb = labels[reldir]
        if not lb.reliable:
            skipped[reldir] = f"unreliable label: {lb.reason}"
            continue
        press = calib.press(reldir)
        try:
            ang, mask = sphere_targets(calib.shape, lb.cx, lb.cy, lb.radius, press.ball_radius_px(mm_per_px), margin_px)
        except ValueError as exc:
            skipped[reldir] = str(exc)
            continue
        if not mask.any():
            skipped[reldir] = "labelled disc lies outside the image"
            continue
        yield reldir, press, ang, mask


def press_samples(
    calib: CalibrationSet, labels: dict[str, PressLabel], reldirs: list[str], mm_per_px: float,
    margin_px: float | None = None,
) -> tuple[Samples, dict[str, str]]:
    """Contact samples of the reliable, not-too-deep presses among ``reldirs``.

    Returns:
        The samples and ``{reldir: reason}`` for the presses left out.
    """
    feats, angs, ids, kept, skipped = [], [], [], [], {}
    for reldir, press, ang, mask in labelled_targets(calib, labels, reldirs, mm_per_px, margin_px, skipped):
        f = pixel_features(torch.from_numpy(calib.image(press))[None])[0]
        feats.append(f[mask])
        angs.append(ang[mask])
        ids.append(torch.full((int(mask.sum()),), len(kept), dtype=torch.int64))
        kept.append(reldir)
    if not kept:
        return Samples(torch.zeros(0, 5), torch.zeros(0, 2), torch.zeros(0, dtype=torch.int64), []), skipped
    return Samples(torch.cat(feats), torch.cat(angs), torch.cat(ids), kept), skipped


def _concat(a: Samples, b: Samples) -> Samples:
    return Samples(torch.cat([a.features, b.features]), torch.cat([a.angles, b.angles]),
                   torch.cat([a.press, b.press]), a.reldirs)


def build_dataset(
    calib: CalibrationSet,
    labels: dict[str, PressLabel],
    mm_per_px: float,
    seed: int = 0,
    test_fraction: float = 0.2,
    margin_px: float | None = None,
    background_ratio: float = 0.2,
    split: dict[str, list[str]] | None = None,
) -> CalibrationData:
    """Split the presses by image (seeded; or take ``split``, e.g. :func:`split_by_diameter`),
    build contact samples per split and add background zero-angle samples,
    ``background_ratio`` of each split's contact count (``seed`` also draws those).

    Raises:
        CalibrationDataError: no usable training press remains.
    """
    if split is None:
        split = split_presses([p.reldir for p in calib.presses], seed, test_fraction)
    train, skipped = press_samples(calib, labels, split["train"], mm_per_px, margin_px)
    test, skipped_test = press_samples(calib, labels, split["test"], mm_per_px, margin_px)
    skipped.update(skipped_test)
    if len(train) == 0:
        raise CalibrationDataError(f"no usable training press in {calib.root}: {skipped}")
    bg_feats = pixel_features(torch.from_numpy(calib.background)[None])[0].reshape(-1, 5)
    perm = torch.randperm(bg_feats.shape[0], generator=torch.Generator().manual_seed(seed + 1))
    n_tr, n_te = int(len(train) * background_ratio), int(len(test) * background_ratio)
    if n_tr + n_te > perm.numel():
        n_tr = perm.numel() * 4 // 5
        n_te = perm.numel() - n_tr
    parts = {"train": perm[:n_tr], "test": perm[n_tr:n_tr + n_te]}

    def with_background(s: Samples, idx: torch.Tensor) -> Samples:
        bg = Samples(bg_feats[idx], torch.zeros(idx.numel(), 2), torch.full((idx.numel(),), -1, dtype=torch.int64),
                     s.reldirs)
        return _concat(s, bg)

    return CalibrationData(with_background(train, parts["train"]), with_background(test, parts["test"]), split,
                           skipped)
