"""Forward colour model for the simulator: ``f(gx, gy, x, y) -> BGR - background``.

The inverse of the calibration MLP: a small MLP maps the gradient angles
``(atan gx, atan gy)`` and the normalised pixel position ``(x/W, y/H)`` to the colour
change against the background, built to be exactly zero for a flat gel. It is fitted on
the same labelled presses (analytic sphere angles inside each disc shrunk by the margin
against the measured colour change), so synthetic images take this sensor's colours.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from torch import nn

from tactile_slam.calibration.catalog import CalibrationDataError, CalibrationSet
from tactile_slam.calibration.dataset import sphere_targets
from tactile_slam.calibration.labels import PressLabel, rim_margin_px
from tactile_slam.calibration.model import check_chunk_pixels, mlp_rows, read_weights
from tactile_slam.geometry.frame import as_tensor

COLOUR_FORMAT_TAG = "tactile-slam-colour-model"


class _ColourMLP(nn.Module):
    """``(N, 4)`` ``[theta_x, theta_y, x/W, y/H]`` -> ``(N, 3)`` BGR difference, exactly zero
    for zero angles (a flat gel looks like the background): ``net(a, p) - net(0, p)``."""

    def __init__(self, hidden: tuple[int, ...]):
        super().__init__()
        sizes = (4, *hidden, 3)
        layers: list[nn.Module] = []
        for i in range(len(sizes) - 1):
            layers.append(nn.Linear(sizes[i], sizes[i + 1]))
            if i < len(sizes) - 2:
                layers.append(nn.ReLU())
        self.net = nn.Sequential(*layers)

    @property
    def layers(self) -> list[nn.Linear]:
        """The linear layers in order (a ReLU follows each but the last)."""
        return [m for m in self.net if isinstance(m, nn.Linear)]

    @staticmethod
    def flat(x: torch.Tensor) -> torch.Tensor:
        """The same pixels with zero angles: ``(N, 4)`` -> ``(N, 4)``."""
        return torch.cat([torch.zeros_like(x[:, :2]), x[:, 2:]], dim=1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.net(x) - self.net(self.flat(x))


class ColourModel:
    """Gradients -> colour change against the background.

    Args:
        hidden: hidden layer sizes of the MLP.
        meta: free metadata stored with the model (sensor, image size, fit error).
        chunk_pixels: on the CPU the MLP runs over at most this many pixels at a time
            (:func:`~tactile_slam.calibration.model.mlp_rows`; 0: all at once).
    """

    def __init__(self, hidden: tuple[int, ...] = (64, 64), meta: dict[str, Any] | None = None,
                 chunk_pixels: int = 4096):
        self.chunk_pixels = check_chunk_pixels(chunk_pixels)
        self.hidden = tuple(int(h) for h in hidden)
        self.net = _ColourMLP(self.hidden).eval()
        self.meta = dict(meta or {})

    @property
    def device(self) -> torch.device:
        return next(self.net.parameters()).device

    def to(self, device: torch.device | str) -> "ColourModel":
        self.net.to(device)
        return self

    @staticmethod
    def features(gradients: torch.Tensor) -> torch.Tensor:
        """``(B, H, W, 2)`` slopes -> ``(B, H, W, 4)`` float32 ``[atan gx, atan gy, x/W, y/H]``."""
        if gradients.ndim != 4 or gradients.shape[-1] != 2:
            raise ValueError(f"gradients must be (B, H, W, 2), got {tuple(gradients.shape)}")
        b, h, w, _ = gradients.shape
        dev = gradients.device
        xs = (torch.arange(w, device=dev, dtype=torch.float32) / w).expand(b, h, w)
        ys = (torch.arange(h, device=dev, dtype=torch.float32) / h)[:, None].expand(b, h, w)
        return torch.cat([torch.atan(gradients.float()), xs[..., None], ys[..., None]], dim=-1)

    @torch.no_grad()
    def __call__(self, gradients: torch.Tensor) -> torch.Tensor:
        """``(B, H, W, 2)`` float slopes ``(dh/dx, dh/dy)`` (a tensor or a numpy array) ->
        ``(B, H, W, 3)`` float32 BGR difference to add to the background (zero slope gives
        about zero)."""
        feats = self.features(as_tensor(gradients, "gradients").to(self.device))
        if not torch.isfinite(feats).all():
            raise ValueError("gradients contain NaN")
        rows = self.chunk_pixels if self.device.type == "cpu" else 0
        x, layers = feats.reshape(-1, 4), self.net.layers
        return (mlp_rows(layers, x, rows) - mlp_rows(layers, self.net.flat(x), rows)).reshape(*feats.shape[:3], 3)

    def save(self, path: str | Path) -> Path:
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        torch.save({"format": COLOUR_FORMAT_TAG, "hidden": list(self.hidden),
                    "state_dict": {k: v.detach().cpu() for k, v in self.net.state_dict().items()},
                    "meta": self.meta}, path)
        return path

    @classmethod
    def load(cls, path: str | Path, device: torch.device | str = "cpu") -> "ColourModel":
        """Load a file written by :meth:`save` (weights-only, strict keys)."""
        path = Path(path)
        obj = read_weights(path, CalibrationDataError, "colour model")
        if not isinstance(obj, dict) or obj.get("format") != COLOUR_FORMAT_TAG:
            raise CalibrationDataError(f"{path} is not a tactile-slam colour model")
        model = cls(tuple(obj["hidden"]), obj.get("meta", {}))
        try:
            model.net.load_state_dict(obj["state_dict"], strict=True)
        except RuntimeError as exc:
            raise CalibrationDataError(f"{path}: state dict does not match: {exc}") from exc
        return model.to(device)


@dataclass
class ColourSamples:
    """``features`` ``(N, 4)`` colour-model input, ``colour`` ``(N, 3)`` BGR difference."""

    features: torch.Tensor
    colour: torch.Tensor


def colour_samples(
    calib: CalibrationSet, labels: dict[str, PressLabel], reldirs: list[str], mm_per_px: float,
    margin_px: float | None = None,
) -> ColourSamples:
    """Samples inside the reliable labelled discs of ``reldirs``: analytic angles and
    position -> measured colour change against the background (``margin_px`` ``None``:
    :func:`~tactile_slam.calibration.labels.rim_margin_px` at ``mm_per_px``)."""
    margin_px = rim_margin_px(mm_per_px) if margin_px is None else margin_px
    feats, cols = [], []
    bg = torch.from_numpy(calib.background)
    for reldir in reldirs:
        lb = labels.get(reldir)
        if lb is None or not lb.reliable:
            continue
        press = calib.press(reldir)
        try:
            ang, mask = sphere_targets(calib.shape, lb.cx, lb.cy, lb.radius, press.ball_radius_px(mm_per_px), margin_px)
        except ValueError:
            continue
        f = ColourModel.features(torch.tan(ang)[None])[0]
        diff = torch.from_numpy(calib.image(press)).float() - bg
        feats.append(f[mask])
        cols.append(diff[mask])
    if not feats:
        raise CalibrationDataError("no reliable labelled press to fit the colour model on")
    return ColourSamples(torch.cat(feats), torch.cat(cols))


def fit_colour_model(
    samples: ColourSamples, hidden: tuple[int, ...] = (64, 64), epochs: int = 40, batch_size: int = 1024,
    lr: float = 3e-3, seed: int = 0, device: str = "cpu",
) -> tuple[ColourModel, float]:
    """Fit a :class:`ColourModel` (L1 on BGR, Adam, step decay x0.5 every ``epochs // 8``).

    Returns:
        The model (eval mode) and its mean absolute colour error on ``samples`` (BGR units).
    """
    if samples.features.shape[0] == 0:
        raise ValueError("no colour samples")
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        model = ColourModel(hidden)
    net = model.net.to(device).train()
    x, y = samples.features.to(device), samples.colour.to(device)
    opt = torch.optim.Adam(net.parameters(), lr=lr)
    sched = torch.optim.lr_scheduler.StepLR(opt, step_size=max(epochs // 8, 1), gamma=0.5)
    gen = torch.Generator().manual_seed(seed)
    for _ in range(epochs):
        perm = torch.randperm(x.shape[0], generator=gen).to(device)
        for i in range(0, x.shape[0], batch_size):
            idx = perm[i:i + batch_size]
            loss = (net(x[idx]) - y[idx]).abs().mean()
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
        sched.step()
    net.eval()
    with torch.no_grad():
        err = sum(float((net(x[i:i + 65536]) - y[i:i + 65536]).abs().sum())
                  for i in range(0, x.shape[0], 65536)) / (3 * x.shape[0])
    return model, err
