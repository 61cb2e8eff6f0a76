"""Held-out accuracy of calibration models against the analytic ball (method.md section 2.2).

Per press, over the labelled disc shrunk by the margin:

* **gradient-angle MAE** (rad): mean ``|f(img) - theta|`` over both angle components of the
  raw model output, the quantity the model is trained on and the SDK reports;
* **normal-angle MAE** (rad): mean angle between the analytic gel normal and the normal
  from the runtime gradients ``G = tan(f(img)) - tan(f(bg))`` (background subtracted).

Totals are pixel-weighted over all presses. By true slope ``|g|`` (bins of
:data:`SLOPE_EDGES`), the **gain** of the runtime gradients: the median over the bin's
pixels of ``G . g / |g|^2``, 1 for an unbiased decoder; a gain below 1 at steep slopes is a
decoder that flattens them, which turns into underestimated tilts downstream
(docs/calibration.md, "Gain by slope"). Any model loadable by
:func:`~tactile_slam.calibration.model.load_model` (either file format) can be scored, so
a new model and the SDK's reference model are compared on identical pixels.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from typing import Any

import torch

from tactile_slam.calibration.catalog import CalibrationDataError, CalibrationSet
from tactile_slam.calibration.dataset import labelled_targets
from tactile_slam.calibration.labels import PressLabel
from tactile_slam.calibration.model import GradientDecoder, GradientMLP, pixel_features
from tactile_slam.geometry.curvature import normals_from_gradients


SLOPE_EDGES: tuple[float, ...] = (0.0, 0.1, 0.2, 0.3, 0.4, 0.5, 0.6, math.inf)


@dataclass(frozen=True)
class SlopeBin:
    """Pixels whose true slope ``|g|`` lies in ``[lo, hi)``: count, median gain of the
    decoded gradients along the true ones (NaN when empty) and normal-angle MAE (rad)."""

    lo: float
    hi: float
    n_px: int
    gain: float
    normal_mae: float


def slope_bins(decoded: torch.Tensor, true: torch.Tensor, normal_err: torch.Tensor,
               edges: tuple[float, ...] = SLOPE_EDGES) -> list[SlopeBin]:
    """Gain and normal error by true slope.

    Args:
        decoded: ``(N, 2)`` decoded gradients.
        true: ``(N, 2)`` true gradients.
        normal_err: ``(N,)`` normal-angle errors (rad).
        edges: increasing bin edges of ``|true|``.
    """
    mag = true.double().norm(dim=1)
    gain = (decoded.double() * true.double()).sum(1) / mag.square().clamp_min(1e-12)
    out = []
    for lo, hi in zip(edges[:-1], edges[1:]):
        sel = (mag >= lo) & (mag < hi)
        n = int(sel.sum())
        out.append(SlopeBin(lo, hi, n, float(gain[sel].median()) if n else math.nan,
                            float(normal_err[sel].double().mean()) if n else math.nan))
    return out


@dataclass(frozen=True)
class PressError:
    """Errors of one press: pixel count, gradient-angle MAE and normal-angle MAE (rad)."""

    reldir: str
    n_px: int
    angle_mae: float
    normal_mae: float


@dataclass
class ModelEvaluation:
    """Per-press errors, pixel-weighted totals (rad), the background's mean ``|angle|`` (rad),
    the presses that could not be scored, with reasons, and the errors by true slope."""

    per_press: list[PressError]
    angle_mae: float
    normal_mae: float
    background_angle: float
    skipped: dict[str, str] = field(default_factory=dict)
    by_slope: list[SlopeBin] = field(default_factory=list)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready summary; angles in rad, normal MAE also in degrees."""
        return {
            "angle_mae_rad": self.angle_mae,
            "normal_mae_rad": self.normal_mae,
            "normal_mae_deg": math.degrees(self.normal_mae),
            "background_mean_abs_angle_rad": self.background_angle,
            "n_presses": len(self.per_press),
            "n_px": sum(p.n_px for p in self.per_press),
            "per_press": [asdict(p) for p in self.per_press],
            "skipped": self.skipped,
            "by_slope": [{k: v if not isinstance(v, float) or math.isfinite(v) else None
                          for k, v in asdict(b).items()} for b in self.by_slope],
        }


def _angle_between(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Angle (rad) between unit vectors ``(..., 3)``; atan2 form, accurate near 0."""
    return torch.atan2(torch.linalg.vector_norm(torch.cross(a, b, dim=-1), dim=-1), (a * b).sum(-1))


@torch.no_grad()
def evaluate_model(
    model: GradientMLP,
    calib: CalibrationSet,
    labels: dict[str, PressLabel],
    reldirs: list[str],
    mm_per_px: float,
    margin_px: float | None = None,
) -> ModelEvaluation:
    """Score ``model`` on the presses ``reldirs`` of ``calib`` (unreliable or too-deep
    labels are skipped and reported).

    Raises:
        CalibrationDataError: a press has no label, or no press can be scored.
    """
    device = next(model.parameters()).device
    bg = torch.from_numpy(calib.background).to(device)
    decoder = GradientDecoder(model, bg, skip_color_dist=0.0)
    errors, skipped, pairs = [], {}, []
    for reldir, press, ang, mask in labelled_targets(calib, labels, reldirs, mm_per_px, margin_px, skipped):
        ang, mask = ang.to(device), mask.to(device)
        img = torch.from_numpy(calib.image(press)).to(device)[None]
        pred = model(pixel_features(img)[0][mask])
        grads = decoder(img)[0][mask]
        n_pred = normals_from_gradients(grads[None, None])[0, 0]
        n_true = normals_from_gradients(torch.tan(ang[mask])[None, None])[0, 0]
        normal_err = _angle_between(n_pred.double(), n_true.double())
        errors.append(PressError(
            reldir, int(mask.sum()), float((pred - ang[mask]).abs().mean()), float(normal_err.mean()),
        ))
        pairs.append((grads.cpu(), torch.tan(ang[mask]).cpu(), normal_err.cpu()))
    if not errors:
        raise CalibrationDataError(f"no press could be scored among {len(reldirs)}: {skipped}")
    n = sum(e.n_px for e in errors)
    bg_angle = float(model(pixel_features(bg[None]).reshape(-1, 5)).abs().mean())
    return ModelEvaluation(
        errors,
        sum(e.angle_mae * e.n_px for e in errors) / n,
        sum(e.normal_mae * e.n_px for e in errors) / n,
        bg_angle,
        skipped,
        slope_bins(*(torch.cat(t) for t in zip(*pairs))),
    )


def format_slope_gain(evals: dict[str, ModelEvaluation]) -> str:
    """Text table: one row per true-slope bin, per model the gain of the decoded
    gradients along the true ones and the normal-angle MAE in degrees."""
    names = list(evals)
    rows = [f"{'true |g|':<14}{'px':>7}" + "".join(f"  {n[:22]:>24}" for n in names),
            f"{'':<14}{'':>7}" + "".join(f"  {'gain':>12}{'normal deg':>12}" for _ in names)]
    for i, b in enumerate(evals[names[0]].by_slope):
        cells = "".join(f"  {e.by_slope[i].gain:>12.3f}{math.degrees(e.by_slope[i].normal_mae):>12.2f}"
                        for e in evals.values())
        rows.append(f"{f'{b.lo:.1f}-{b.hi:.1f}':<14}{b.n_px:>7}" + cells)
    return "\n".join(rows)


def format_comparison(evals: dict[str, ModelEvaluation]) -> str:
    """Side-by-side text table: one row per press, two columns per model (gradient-angle
    MAE in rad, normal-angle MAE in degrees), pixel-weighted totals last."""
    names = list(evals)
    first = evals[names[0]]
    rows = [f"{'press':<14}{'px':>7}" + "".join(f"  {n[:22]:>24}" for n in names),
            f"{'':<14}{'':>7}" + "".join(f"  {'angle rad':>12}{'normal deg':>12}" for _ in names)]
    by_name = {n: {p.reldir: p for p in e.per_press} for n, e in evals.items()}
    for p in first.per_press:
        cells = []
        for n in names:
            q = by_name[n].get(p.reldir)
            cells.append(f"  {q.angle_mae:>12.4f}{math.degrees(q.normal_mae):>12.2f}" if q else f"  {'-':>12}{'-':>12}")
        rows.append(f"{p.reldir:<14}{p.n_px:>7}" + "".join(cells))
    total_px = sum(p.n_px for p in first.per_press)
    rows.append(f"{'ALL':<14}{total_px:>7}" + "".join(
        f"  {e.angle_mae:>12.4f}{math.degrees(e.normal_mae):>12.2f}" for e in evals.values()))
    return "\n".join(rows)
