"""Automatic contact-circle labels for ball presses, label files and overlay images.

Detection (no model needed, no thresholds tuned to one data set):

1. colour distance ``d = ||blur(img - background)||``; a press's *changed region* is the
   largest connected set of pixels whose ``d`` exceeds the image's own noise level
   (median + ``noise_sigmas`` robust standard deviations of ``d``, the press covering a
   minority of the image);
2. rays are cast from the region's ``d``-weighted centroid; along each ray ``d`` peaks at
   the **contact rim**: the gel follows the sphere inside the contact, so its slope (and
   colour change) grows up to the rim and decays outside it;
3. a circle is fitted to the per-ray peaks (algebraic fit, trimmed of outliers); rays
   that leave the image before their peak, or before the previous round's rim, are
   dropped (unobserved), so presses cut by the border keep an unbiased circle; steps 2-3
   repeat from the new centre until the circle settles;
4. steps 2-3 run from several starts (the centroid and points around it), because a
   colour feature inside the contact can hold a fit that starts near it; the contact rim
   encloses every such feature, so the **largest** circle that passes every check below
   is the label (flagged when a larger fit around its centre fails only for the border).

A label is flagged unreliable (kept in the file, never trained on) when too little of
the fitted circle lies inside the image, the rim is not circular, or it contradicts the
ball geometry: a contact radius ``a`` must be below the ball radius ``R`` and imply an
indentation ``R - sqrt(R^2 - a^2)`` no deeper than the sensor's maximum and at least
1 px deep. A press without contact is flagged by :func:`label_presses`.

Label files are CSV with header ``experiment_reldir,cx,cy,radius`` (pixels, ``cx`` the
column, ``cy`` the row) and optional ``reliable`` (1/0) and ``reason`` columns. Rows of a
hand-edited file override detection for the presses they list.
"""

from __future__ import annotations

import csv
import math
from dataclasses import dataclass, replace
from pathlib import Path
from typing import NamedTuple

import cv2
import numpy as np

from tactile_slam.calibration.catalog import CalibrationDataError, CalibrationSet

LABEL_COLUMNS = ("experiment_reldir", "cx", "cy", "radius")

PIXEL_SCALE_MM = 0.0634
"""Scale (mm per pixel, the GelSight Mini's at 320x240) at which the calibration's pixel
settings are given: the detector's and the rim margin. A press set at another scale
has them converted to its own pixels (:meth:`DetectionConfig.at_scale`,
:func:`rim_margin_px`), so the same physical tolerances apply, e.g. to presses
recorded at 640x480."""

RIM_MARGIN_PX = 4.0
"""Pixels (at :data:`PIXEL_SCALE_MM`) inside a label's rim left out of training and
evaluation: the rim's position is uncertain and the gel bends most there."""


def to_scale(px: float, mm_per_px: float) -> float:
    """A length of ``px`` pixels at :data:`PIXEL_SCALE_MM`, in pixels at ``mm_per_px``."""
    if not (math.isfinite(mm_per_px) and mm_per_px > 0):
        raise ValueError(f"mm_per_px must be finite and > 0, got {mm_per_px}")
    return px if mm_per_px == PIXEL_SCALE_MM else px * PIXEL_SCALE_MM / mm_per_px


def rim_margin_px(mm_per_px: float) -> float:
    """:data:`RIM_MARGIN_PX` in pixels of an image at ``mm_per_px`` (4 px on the Mini)."""
    return to_scale(RIM_MARGIN_PX, mm_per_px)


class NoContactError(CalibrationDataError):
    """A press image shows no contact that could be labelled."""


@dataclass(frozen=True)
class PressLabel:
    """Contact circle of one press in pixels (``cx`` column, ``cy`` row, ``radius``).

    ``reliable`` is False when the label must not be trained on; ``reason`` says why.
    ``source`` is ``"auto"`` (detected) or ``"file"`` (read from a labels file). A press
    without contact has a NaN circle (flagged, reason ``"no contact ..."``).
    ``visible`` is the fraction of the rim inside the image, ``residual_px`` the median
    distance of the rim points to the circle (both NaN for file labels).
    """

    reldir: str
    cx: float
    cy: float
    radius: float
    reliable: bool = True
    reason: str = ""
    source: str = "auto"
    visible: float = math.nan
    residual_px: float = math.nan


@dataclass(frozen=True)
class DetectionConfig:
    """Detector settings; all but the geometry are dimensionless or relative. Lengths
    (``blur_sigma``, ``settle_px``, ``max_residual_px``, ``min_radius_px``,
    ``min_indentation_px``) are pixels at :data:`PIXEL_SCALE_MM`; :meth:`at_scale`
    converts them for another image scale (:func:`label_presses` does so).

    ``noise_sigmas``: changed-pixel threshold in robust noise standard deviations.
    ``n_rays``: rays cast from the centre. ``iterations``: most ray-and-fit rounds per
    start. ``starts``: fits started from the changed region's centroid and ``starts - 1``
    points on a circle of half the region's equivalent radius around it. ``settle_px``:
    a fit has settled when its circle (centre shift plus radius change) moves less than
    this in a round. ``min_visible``: least fraction of the rim inside the image for a
    reliable label. ``max_residual_px``: largest median distance of rim points to the
    fitted circle. ``min_radius_px``: smallest reliable radius. ``min_indentation_px``:
    shallowest reliable indentation ``R - sqrt(R^2 - a^2)``; a contact narrower than that
    of a 1-px-deep press (``a < sqrt(2 R - 1)``) belongs to a smaller ball than catalogued.
    """

    noise_sigmas: float = 8.0
    blur_sigma: float = 1.0
    n_rays: int = 180
    iterations: int = 12
    starts: int = 9
    settle_px: float = 0.5
    min_visible: float = 0.6
    max_residual_px: float = 3.0
    min_radius_px: float = 8.0
    min_indentation_px: float = 1.0

    def __post_init__(self) -> None:
        for name, least in (("iterations", 1), ("starts", 1), ("n_rays", 8)):
            if getattr(self, name) < least:
                raise ValueError(f"DetectionConfig.{name} must be >= {least}, got {getattr(self, name)}")
        if not self.settle_px > 0:
            raise ValueError(f"DetectionConfig.settle_px must be > 0, got {self.settle_px}")

    def at_scale(self, mm_per_px: float) -> "DetectionConfig":
        """These settings for images at ``mm_per_px``: lengths converted from pixels at
        :data:`PIXEL_SCALE_MM` (the same settings at that scale)."""
        return replace(self, **{name: to_scale(getattr(self, name), mm_per_px)
                                for name in ("blur_sigma", "settle_px", "max_residual_px", "min_radius_px",
                                             "min_indentation_px")})


def _fit_circle(x: np.ndarray, y: np.ndarray) -> tuple[float, float, float]:
    """Algebraic (Kasa) least-squares circle through points ``(N,)``, ``(N,)``."""
    a = np.stack([x, y, np.ones_like(x)], axis=1)
    sol = np.linalg.lstsq(a, x * x + y * y, rcond=None)[0]
    cx, cy = sol[0] / 2.0, sol[1] / 2.0
    return float(cx), float(cy), float(math.sqrt(max(sol[2] + cx * cx + cy * cy, 0.0)))


def _trimmed_circle(x: np.ndarray, y: np.ndarray, rounds: int = 3) -> tuple[float, float, float, float]:
    """Circle fit that drops points beyond 2.5 robust sigmas (min 1 px); returns ``cx, cy, r, median residual``."""
    keep = np.ones(x.shape, dtype=bool)
    for _ in range(rounds):
        cx, cy, r = _fit_circle(x[keep], y[keep])
        res = np.abs(np.hypot(x - cx, y - cy) - r)
        new_keep = res < max(2.5 * 1.4826 * float(np.median(res[keep])), 1.0)
        if new_keep.sum() < 3:
            break
        keep = new_keep
    cx, cy, r = _fit_circle(x[keep], y[keep])
    res = np.abs(np.hypot(x[keep] - cx, y[keep] - cy) - r)
    return cx, cy, r, float(np.median(res))


def indentation_px(radius: float, ball_radius_px: float) -> float:
    """Sphere-cap depth ``R - sqrt(R^2 - a^2)`` (px) of a contact of radius ``a``; inf if ``a >= R``."""
    if radius >= ball_radius_px:
        return math.inf
    return ball_radius_px - math.sqrt(ball_radius_px**2 - radius**2)


class _RimFit(NamedTuple):
    """One start's circle (px), the fraction of that circle inside the image, the median
    residual of the rim points, and whether the fit settled."""

    cx: float
    cy: float
    radius: float
    visible: float
    residual: float
    settled: bool


def _settled(fits: list[_RimFit], tol: float) -> bool:
    """Whether the last circle of ``fits`` repeats the one before it, or the one two
    rounds before (a fit that alternates between two circles), to within ``tol`` px
    (centre shift plus radius change)."""
    def move(a: _RimFit, b: _RimFit) -> float:
        return math.hypot(a.cx - b.cx, a.cy - b.cy) + abs(a.radius - b.radius)
    return any(len(fits) > k and move(fits[-1], fits[-1 - k]) < tol for k in (1, 2))


def _visible_fraction(cx: float, cy: float, radius: float, shape: tuple[int, int], n: int) -> float:
    """Fraction of ``n`` points evenly spaced on the circle that lie inside an image of ``shape`` = (H, W)."""
    t = np.linspace(0.0, 2.0 * math.pi, n, endpoint=False)
    x, y = cx + radius * np.cos(t), cy + radius * np.sin(t)
    return float(((x >= 0) & (x <= shape[1] - 1) & (y >= 0) & (y <= shape[0] - 1)).mean())


def _rim_fit(dist: np.ndarray, threshold: float, cx: float, cy: float, ball_radius_px: float,
             cfg: DetectionConfig) -> _RimFit:
    """Rays from ``(cx, cy)`` over the ``(H, W)`` colour distance, a circle through their
    peaks, repeated from the circle's centre until it settles (at most
    ``cfg.iterations`` rounds). A fit that alternates between two circles keeps the one
    with the smaller residual. The radius is NaN when fewer than 8 rays find a peak."""
    h, w = dist.shape
    angles = np.linspace(0.0, 2.0 * math.pi, cfg.n_rays, endpoint=False)
    step = 0.5
    radii = np.arange(1.0, ball_radius_px, step, dtype=np.float32)
    cos, sin = np.cos(angles)[:, None], np.sin(angles)[:, None]
    fits: list[_RimFit] = []
    for _ in range(cfg.iterations):
        rx = (cx + cos * radii).astype(np.float32)
        ry = (cy + sin * radii).astype(np.float32)
        prof = cv2.remap(dist, rx, ry, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=-1.0)
        inside = (rx >= 0) & (rx <= w - 1) & (ry >= 0) & (ry <= h - 1)
        peak = prof.argmax(axis=1)
        # a ray counts when it stays in the image 2 px beyond both its peak and the rim of
        # the previous round's circle (a ray that leaves the image short of the rim cannot
        # have seen it: the peak it found lies inside the contact), and the peak is interior
        # to the search range and above the noise threshold
        rim = 0 if not fits else int(np.searchsorted(radii, fits[-1].radius))
        beyond = np.minimum(np.maximum(peak, rim) + int(2.0 / step), radii.size - 1)
        observed = np.cumprod(inside, axis=1)[np.arange(cfg.n_rays), beyond].astype(bool)
        ok = observed & (peak > 0) & (peak < radii.size - 1) & (prof[np.arange(cfg.n_rays), peak] > threshold)
        if ok.sum() < 8:
            return fits[-1] if fits else _RimFit(cx, cy, math.nan, math.nan, math.nan, False)
        # sub-sample peak: vertex of the parabola through the peak and its neighbours
        rows = np.arange(cfg.n_rays)[ok]
        p0, pm, pp = prof[rows, peak[ok]], prof[rows, peak[ok] - 1], prof[rows, peak[ok] + 1]
        curv = pm - 2.0 * p0 + pp
        frac = np.where(curv < 0, 0.5 * (pm - pp) / np.where(curv < 0, curv, -1.0), 0.0).clip(-0.5, 0.5)
        rad = radii[peak[ok]] + frac * step
        cx, cy, r, residual = _trimmed_circle(cx + np.cos(angles[ok]) * rad, cy + np.sin(angles[ok]) * rad)
        fits.append(_RimFit(cx, cy, r, _visible_fraction(cx, cy, r, (h, w), cfg.n_rays), residual, False))
        if _settled(fits, cfg.settle_px):
            break
    best = min(fits[-2:], key=lambda f: f.residual)
    return best._replace(settled=_settled(fits, cfg.settle_px))


def _shape_problems(fit: _RimFit, ball_radius_px: float, max_indentation_px: float, cfg: DetectionConfig
                    ) -> list[str]:
    """Why a fitted circle is no contact rim of this ball, wherever it lies (empty when it may be)."""
    reasons = []
    if fit.residual > cfg.max_residual_px:
        reasons.append(f"rim is not circular (median residual {fit.residual:.1f} px)")
    if fit.radius < cfg.min_radius_px:
        reasons.append(f"contact radius {fit.radius:.1f} px < {cfg.min_radius_px:g} px")
    depth = indentation_px(fit.radius, ball_radius_px)
    if depth > max_indentation_px:
        reasons.append(
            f"contact radius {fit.radius:.1f} px implies indentation {depth:.1f} px > max {max_indentation_px:.1f} px"
        )
    elif depth < cfg.min_indentation_px:
        reasons.append(
            f"contact radius {fit.radius:.1f} px implies indentation {depth:.2f} px < {cfg.min_indentation_px:g} px "
            f"for a ball of radius {ball_radius_px:.1f} px: is its diameter in catalog.csv right?"
        )
    return reasons


def _label_problems(fit: _RimFit, ball_radius_px: float, max_indentation_px: float, cfg: DetectionConfig
                    ) -> list[str]:
    """Why a fitted circle cannot be trained on (empty when it can): :func:`_shape_problems`,
    after a fit that did not settle or a rim mostly outside the image."""
    reasons = [] if fit.settled else [f"rim fit did not settle within {cfg.iterations} rounds"]
    if fit.visible < cfg.min_visible:
        reasons.append(f"only {fit.visible:.0%} of the rim is inside the image")
    return reasons + _shape_problems(fit, ball_radius_px, max_indentation_px, cfg)


def detect_contact_circle(
    image: np.ndarray,
    background: np.ndarray,
    ball_radius_px: float,
    max_indentation_px: float,
    cfg: DetectionConfig = DetectionConfig(),
    reldir: str = "",
) -> PressLabel:
    """Detect the contact circle of a ball press.

    Args:
        image: ``(H, W, 3)`` BGR press image (uint8 or float).
        background: ``(H, W, 3)`` BGR background, same size.
        ball_radius_px: ball radius in pixels.
        max_indentation_px: deepest plausible indentation in pixels.
        cfg: detector settings in this image's pixels (``DetectionConfig().at_scale(mm_per_px)``
            for an image at another scale than :data:`PIXEL_SCALE_MM`).
        reldir: press name carried into the label and error messages.

    Returns:
        The label; ``reliable`` False with a ``reason`` when it fails a check.

    Raises:
        NoContactError: no changed region large enough for a 1-px-deep press.
        ValueError: mismatched or non-finite inputs.
    """
    if image.shape != background.shape or image.ndim != 3 or image.shape[2] != 3:
        raise ValueError(f"image {image.shape} and background {background.shape} must both be (H, W, 3)")
    diff = image.astype(np.float32) - background.astype(np.float32)
    if not np.isfinite(diff).all():
        raise ValueError(f"press {reldir}: image or background has non-finite values")
    h, w = diff.shape[:2]
    dist = np.linalg.norm(cv2.GaussianBlur(diff, (0, 0), cfg.blur_sigma), axis=2).astype(np.float32)
    med = float(np.median(dist))
    spread = 1.4826 * float(np.median(np.abs(dist - med)))
    threshold = med + cfg.noise_sigmas * max(spread, 0.5)  # floor: half a grey level (noise-free images)
    changed = cv2.morphologyEx((dist > threshold).astype(np.uint8), cv2.MORPH_OPEN, np.ones((3, 3), np.uint8))
    n, lab, stats, _ = cv2.connectedComponentsWithStats(changed, connectivity=8)
    min_area = 2.0 * math.pi * ball_radius_px  # contact area of a 1-px-deep press: pi * (2 R * 1)
    if n < 2 or stats[1:, cv2.CC_STAT_AREA].max() < min_area:
        largest = 0 if n < 2 else int(stats[1:, cv2.CC_STAT_AREA].max())
        raise NoContactError(
            f"press {reldir or '?'}: no visible contact (largest changed region {largest} px < {min_area:.0f} px "
            f"at colour distance > {threshold:.1f}); remove it from catalog.csv or give its label in a labels file"
        )
    region = lab == 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
    wgt = np.where(region, dist, 0.0)
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float32)
    cx, cy = float((wgt * xs).sum() / wgt.sum()), float((wgt * ys).sum() / wgt.sum())

    ring = 0.5 * math.sqrt(float(region.sum()) / math.pi)
    turns = np.linspace(0.0, 2.0 * math.pi, cfg.starts - 1, endpoint=False)
    starts = [(cx, cy)] + [(cx + ring * math.cos(a), cy + ring * math.sin(a)) for a in turns]
    fits = [_rim_fit(dist, threshold, sx, sy, ball_radius_px, cfg) for sx, sy in starts]
    if not any(math.isfinite(f.radius) for f in fits):
        raise NoContactError(
            f"press {reldir or '?'}: no contact rim found (from no start did 8 of {cfg.n_rays} rays see a peak "
            "of the colour distance inside the image)"
        )
    checked = [(f, _label_problems(f, ball_radius_px, max_indentation_px, cfg))
               for f in fits if math.isfinite(f.radius)]
    passing = [f for f, problems in checked if not problems]
    if passing:
        best = max(passing, key=lambda f: f.radius)
        # the contact rim encloses every colour feature: a circle around this one's centre, larger
        # by more than a rim's residual, that fails only for the border (or for not settling)
        # may be the rim, and this a feature inside it
        outer = [f for f, problems in checked if problems
                 and not _shape_problems(f, ball_radius_px, max_indentation_px, cfg)
                 and f.radius > best.radius + cfg.max_residual_px
                 and math.hypot(f.cx - best.cx, f.cy - best.cy) < f.radius]
        if outer:
            return PressLabel(reldir, best.cx, best.cy, best.radius, False,
                              f"inside a larger rim fit (radius {max(f.radius for f in outer):.1f} px) that is cut by "
                              "the image border or did not settle", "auto", best.visible, best.residual)
        return PressLabel(reldir, best.cx, best.cy, best.radius, True, "", "auto", best.visible, best.residual)
    best, problems = checked[0]  # nothing passes: the centroid start's fit (or the first that found a rim), flagged
    return PressLabel(reldir, best.cx, best.cy, best.radius, False, "; ".join(problems), "auto", best.visible,
                      best.residual)


def read_labels(path: str | Path) -> dict[str, PressLabel]:
    """Read a labels CSV (``experiment_reldir,cx,cy,radius[,reliable][,reason]``) keyed by reldir.
    A flagged row (``reliable`` 0) may leave ``cx,cy,radius`` empty: a press without contact."""
    path = Path(path)
    if not path.is_file():
        raise CalibrationDataError(f"labels file not found: {path}")
    with path.open(newline="") as f:
        reader = csv.DictReader(f)
        fields = [c.strip() for c in (reader.fieldnames or [])]
        if fields[:4] != list(LABEL_COLUMNS):
            raise CalibrationDataError(f"{path}: header must start with {','.join(LABEL_COLUMNS)}, got {fields}")
        out = {}
        for i, row in enumerate(reader, start=2):
            row = {k.strip(): (v or "").strip() for k, v in row.items() if k is not None}
            try:
                cx, cy, rad = (float(row[k] or "nan") for k in ("cx", "cy", "radius"))
            except ValueError as exc:
                raise CalibrationDataError(f"{path}:{i}: cx, cy, radius must be numbers: {row}") from exc
            reliable = row.get("reliable", "1") in ("", "1", "true", "True", "yes")
            no_circle = not reliable and not any(map(math.isfinite, (cx, cy, rad)))  # a flagged press without contact
            if not no_circle and (not all(map(math.isfinite, (cx, cy, rad))) or rad <= 0):
                raise CalibrationDataError(f"{path}:{i}: need finite cx, cy and radius > 0, got {row}")
            reldir = row["experiment_reldir"]
            out[reldir] = PressLabel(reldir, cx, cy, rad, reliable, row.get("reason", ""), "file")
    return out


def write_labels(path: str | Path, labels: list[PressLabel]) -> Path:
    """Write labels as CSV: ``experiment_reldir,cx,cy,radius,reliable,reason,source`` (the
    circle left empty for a press without contact)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("w", newline="") as f:
        wr = csv.writer(f)
        wr.writerow([*LABEL_COLUMNS, "reliable", "reason", "source"])
        for lb in labels:
            circle = [f"{v:.2f}" if math.isfinite(v) else "" for v in (lb.cx, lb.cy, lb.radius)]
            wr.writerow([lb.reldir, *circle, int(lb.reliable), lb.reason, lb.source])
    return path


def label_presses(
    calib: CalibrationSet,
    mm_per_px: float,
    max_indentation_mm: float,
    overrides: dict[str, PressLabel] | None = None,
    cfg: DetectionConfig = DetectionConfig(),
) -> list[PressLabel]:
    """Label every press of ``calib`` in catalog order, with ``cfg`` converted to the
    set's scale (:meth:`DetectionConfig.at_scale`).

    Presses listed in ``overrides`` (e.g. from :func:`read_labels`) take that label and
    are not detected; the others are detected with :func:`detect_contact_circle`. A
    detected press without contact is flagged (reason ``"no contact ..."``, its circle NaN),
    so that training and evaluation skip it.

    Raises:
        CalibrationDataError: an override names a press not in the catalog.
        NoContactError: no press shows contact (and none has an override).
    """
    overrides = overrides or {}
    unknown = sorted(set(overrides) - {p.reldir for p in calib.presses})
    if unknown:
        raise CalibrationDataError(f"labels name presses not in the catalog: {unknown[:5]}")
    cfg = cfg.at_scale(mm_per_px)
    out = []
    for press in calib.presses:
        if press.reldir in overrides:
            out.append(overrides[press.reldir])
            continue
        try:
            out.append(
                detect_contact_circle(
                    calib.image(press), calib.background, press.ball_radius_px(mm_per_px),
                    max_indentation_mm / mm_per_px, cfg, press.reldir,
                )
            )
        except NoContactError as exc:
            out.append(PressLabel(press.reldir, math.nan, math.nan, math.nan, False, f"no contact ({exc})"))
    if not any(math.isfinite(lb.radius) for lb in out):
        raise NoContactError(f"no press in {calib.root} shows contact, first: {out[0].reason}")
    return out


def draw_label(image: np.ndarray, label: PressLabel, margin_px: float = RIM_MARGIN_PX) -> np.ndarray:
    """Copy of a ``(H, W, 3)`` uint8 image with the circle (green: reliable, red: flagged),
    the trained disc (radius - margin, thin) and the centre drawn in; an unchanged copy for a
    label without circle (a press without contact)."""
    out = image.copy()
    if not math.isfinite(label.radius):  # a press without contact: nothing to draw
        return out
    colour = (0, 200, 0) if label.reliable else (0, 0, 255)
    shift = 4  # sub-pixel drawing: coordinates in 1/16 px
    c = (round(label.cx * 16), round(label.cy * 16))
    cv2.circle(out, c, round(label.radius * 16), colour, 1, cv2.LINE_AA, shift)
    if label.radius > margin_px:
        cv2.circle(out, c, round((label.radius - margin_px) * 16), (255, 255, 255), 1, cv2.LINE_AA, shift)
    cv2.drawMarker(out, (round(label.cx), round(label.cy)), colour, cv2.MARKER_CROSS, 7, 1)
    return out


def write_overlays(calib: CalibrationSet, labels: list[PressLabel], out_dir: str | Path,
                   columns: int = 6, margin_px: float = RIM_MARGIN_PX) -> Path:
    """Write ``out_dir/<reldir with '/' as '_'>.png`` per press and ``out_dir/overview.png``,
    a grid of half-size tiles captioned with the press name and radius; returns the overview path."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    tiles = []
    for lb in labels:
        img = draw_label(calib.image(calib.press(lb.reldir)), lb, margin_px)
        cv2.imwrite(str(out_dir / f"{lb.reldir.replace('/', '_')}.png"), img)
        tile = cv2.resize(img, (img.shape[1] // 2, img.shape[0] // 2), interpolation=cv2.INTER_AREA)
        text = f"{lb.reldir} " + (f"r={lb.radius:.1f}" if math.isfinite(lb.radius) else "no contact") \
            + ("" if lb.reliable else " FLAGGED")
        cv2.putText(tile, text, (3, 12), cv2.FONT_HERSHEY_SIMPLEX, 0.35,
                    (255, 255, 255) if lb.reliable else (0, 0, 255), 1, cv2.LINE_AA)
        tiles.append(tile)
    while len(tiles) % columns:
        tiles.append(np.zeros_like(tiles[0]))
    grid = np.vstack([np.hstack(tiles[i:i + columns]) for i in range(0, len(tiles), columns)])
    path = out_dir / "overview.png"
    cv2.imwrite(str(path), grid)
    return path
