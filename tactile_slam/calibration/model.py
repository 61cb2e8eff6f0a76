"""Calibration model: per-pixel MLP from colour and position to gradient angles.

Two file formats load here (method.md section 2.4):

* the GelSight SDK's ``nnmodel.pth``: a bare ``state_dict`` with layers ``fc1..fc4``;
* tactile-slam's own ``.pt`` files: ``{"format": "tactile-slam-calibration",
  "hidden": [...], "state_dict": ..., "meta": {...}}``.

Both are loaded weights-only with a strict key check.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from tactile_slam.config import ContactConfig, SensorConfig
from tactile_slam.geometry.contact import colour_distance
from tactile_slam.geometry.frame import as_tensor
from tactile_slam.geometry.morphology import dilate

FORMAT_TAG = "tactile-slam-calibration"


class CalibrationModelError(ValueError):
    """A calibration model file is missing or malformed."""


class GradientMLP(nn.Module):
    """MLP ``5 -> hidden... -> 2`` with ReLU; layers are named ``fc1..fc{n+1}`` so the
    default ``(32, 32, 32)`` is state-dict compatible with the SDK's model.

    Input per pixel: ``[B/255, G/255, R/255, x/W, y/H]``; output: gradient angles
    ``(theta_x, theta_y)`` in radians (the slope is their tangent).
    """

    def __init__(self, hidden: tuple[int, ...] = (32, 32, 32)):
        super().__init__()
        self.hidden = tuple(int(h) for h in hidden)
        sizes = (5, *self.hidden, 2)
        for i in range(len(sizes) - 1):
            self.add_module(f"fc{i + 1}", nn.Linear(sizes[i], sizes[i + 1]))
        self.n_layers = len(sizes) - 1

    @property
    def layers(self) -> list[nn.Linear]:
        """The linear layers in order (a ReLU follows each but the last)."""
        return [getattr(self, f"fc{i}") for i in range(1, self.n_layers + 1)]

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """``(N, 5)`` -> ``(N, 2)`` angles in rad."""
        for layer in self.layers[:-1]:
            x = torch.relu(layer(x))
        return self.layers[-1](x)


def read_weights(path: str | Path, error: type[Exception], what: str) -> Any:
    """The object in a ``torch.save`` file, read weights-only onto the CPU; ``error``
    (naming ``what`` and the path) when the file is missing or cannot be read."""
    path = Path(path)
    if not path.is_file():
        raise error(f"{what} not found: {path}")
    try:
        return torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # torch raises several types for corrupt files
        raise error(f"cannot read {what} {path}: {exc}") from exc


def check_chunk_pixels(value: int) -> int:
    """A ``chunk_pixels`` setting: an integer >= 0 (0: all pixels at once)."""
    if isinstance(value, bool) or not isinstance(value, int) or value < 0:
        raise ValueError(f"chunk_pixels must be an integer >= 0, got {value!r}")
    return value


@torch.no_grad()
def mlp_rows(layers: list[nn.Linear], x: torch.Tensor, rows: int) -> torch.Tensor:
    """Inference of ``Linear -> ReLU -> ... -> Linear`` over the rows of ``x``, at most
    ``rows`` at a time (``0``: all at once).

    Each hidden layer writes into one buffer of ``rows`` rows that every chunk reuses,
    and its ReLU runs in place: on the CPU a new tensor per chunk and layer, and the
    extra pass of an out-of-place ReLU, cost more than the products themselves
    (``docs/calibration.md``, "Decoding speed"). Equal to the module's forward to
    rounding.

    Args:
        layers: the linear layers in order.
        x: ``(N, C_in)``.
        rows: chunk size, ``>= 0``.

    Returns:
        ``(N, C_out)``.
    """
    check_chunk_pixels(rows)
    if x.ndim != 2 or x.shape[1] != layers[0].in_features:
        raise ValueError(f"mlp_rows: x must be (N, {layers[0].in_features}), got {tuple(x.shape)}")
    n = len(x)
    step = min(rows or n, n)
    out = x.new_empty(n, layers[-1].out_features)
    if n == 0:
        return out
    buffers = [x.new_empty(step, layer.out_features) for layer in layers[:-1]]
    for i in range(0, n, step):
        h = x[i:i + step]
        k = len(h)
        for layer, buf in zip(layers[:-1], buffers):
            h = torch.addmm(layer.bias, h, layer.weight.t(), out=buf[:k]).relu_()
        torch.addmm(layers[-1].bias, h, layers[-1].weight.t(), out=out[i:i + k])
    return out


def pixel_grid(h: int, w: int, device: torch.device | str = "cpu") -> torch.Tensor:
    """Normalised pixel positions ``(x/W, y/H)``: ``(H, W, 2)`` float32."""
    xs = (torch.arange(w, device=device, dtype=torch.float32) / w).expand(h, w)
    ys = (torch.arange(h, device=device, dtype=torch.float32) / h)[:, None].expand(h, w)
    return torch.stack([xs, ys], dim=-1)


def pixel_features(bgr: torch.Tensor) -> torch.Tensor:
    """Per-pixel model input from raw BGR images.

    Args:
        bgr: ``(B, H, W, 3)`` uint8 or float in ``[0, 255]``.

    Returns:
        ``(B, H, W, 5)`` float32: ``B/255, G/255, R/255, x/W, y/H``.
    """
    b, h, w, _ = bgr.shape
    col = bgr.float() / 255.0
    return torch.cat([col, pixel_grid(h, w, bgr.device).expand(b, h, w, 2)], dim=-1)


def save_model(path: str | Path, model: GradientMLP, meta: dict[str, Any] | None = None) -> None:
    """Write a tactile-slam model file (state dict + hidden sizes + metadata)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    torch.save(
        {
            "format": FORMAT_TAG,
            "hidden": list(model.hidden),
            "state_dict": {k: v.detach().cpu().float() for k, v in model.state_dict().items()},
            "meta": meta or {},
        },
        path,
    )


def load_model(path: str | Path, device: torch.device | str = "cpu") -> tuple[GradientMLP, dict[str, Any]]:
    """Load a model in either format onto ``device`` in eval mode.

    Returns:
        ``(model, meta)``; ``meta`` is empty for SDK files.
    """
    path = Path(path)
    obj = read_weights(path, CalibrationModelError, "calibration model")
    if isinstance(obj, dict) and obj.get("format") == FORMAT_TAG:
        hidden = tuple(obj["hidden"])
        state, meta = obj["state_dict"], dict(obj.get("meta", {}))
    elif isinstance(obj, dict) and all(isinstance(v, torch.Tensor) for v in obj.values()):
        n = len([k for k in obj if k.endswith(".weight")])
        if n < 2 or "fc1.weight" not in obj:
            raise CalibrationModelError(f"{path} is not an MLP state dict (keys {sorted(obj)[:6]})")
        hidden = tuple(obj[f"fc{i}.weight"].shape[0] for i in range(1, n))
        state, meta = obj, {}
    else:
        raise CalibrationModelError(f"{path} is neither a tactile-slam model nor an SDK state dict")
    model = GradientMLP(hidden)
    try:
        model.load_state_dict(state, strict=True)
    except RuntimeError as exc:
        raise CalibrationModelError(f"{path}: state dict does not match the MLP: {exc}") from exc
    return model.to(device).eval(), meta


class ModelSensorWarning(UserWarning):
    """A calibration model was trained on another sensor than the one configured."""


def model_sensor_mismatch(meta: dict[str, Any], sensor: SensorConfig) -> str | None:
    """Why a model whose ``meta`` (from :func:`load_model`) is unfit for ``sensor``, or
    ``None``: another field of view (image size times ``mm_per_px`` differing by more
    than 1 % on either axis). The model reads positions as fractions of the image, so
    the same gel at another resolution is fine; another field of view puts every learnt
    position elsewhere on the gel. Sensor names are not compared (configs name the same
    sensor differently). SDK files carry no ``meta`` and are not checked."""
    size, mm = meta.get("image_size"), meta.get("mm_per_px")
    if size is not None and mm is not None:
        trained = np.asarray(size, dtype=float) * float(mm)
        now = np.asarray(sensor.shape, dtype=float) * sensor.mm_per_px
        if (np.abs(trained / now - 1.0) > 0.01).any():
            return (f"the model was trained on a {trained[1]:.2f} x {trained[0]:.2f} mm field of view, "
                    f"the sensor has {now[1]:.2f} x {now[0]:.2f} mm (image size times mm_per_px)")
    return None


class GradientDecoder:
    """Colour image -> surface gradients with the background's gradients subtracted.

    ``G = tan(f(img)) - tan(f(bg))``. Pixels whose colour stays within
    ``skip_color_dist`` of the background (after a small dilation) are not evaluated:
    their image equals the background there, so their gradient is zero.

    Args:
        model: the calibration MLP.
        background: ``(H, W, 3)`` float BGR background (mean of contact-free frames), a
            tensor or a numpy array (e.g. a source's ``background``).
        skip_color_dist: colour distance under which a pixel is skipped (default
            ``contact.mlp_skip_color_dist``, what the pipelines use); ``0`` evaluates every pixel.
        max_angle: angles are clamped to ``[-max_angle, max_angle]`` rad before tan.
        chunk_pixels: on the CPU the model runs over at most this many pixels at a time,
            so that its layer outputs stay in cache (one product over the changed pixels
            of a batch of full frames is several times slower; ``docs/calibration.md``);
            ``0`` or another device: all at once. Results do not depend on it beyond rounding.

    Attributes:
        grid: ``(H * W, 2)`` normalised pixel positions ``(x/W, y/H)``, row-major.
        bg_slopes: ``(H * W, 2)`` the background's slopes, row-major.
    """

    def __init__(
        self,
        model: GradientMLP,
        background: torch.Tensor,
        skip_color_dist: float = ContactConfig.mlp_skip_color_dist,
        max_angle: float = 1.4,
        chunk_pixels: int = 4096,
    ):
        background = as_tensor(background, "background")
        if background.ndim != 3 or background.shape[-1] != 3:
            raise ValueError(f"background must be (H, W, 3), got {tuple(background.shape)}")
        self.model = model
        self.device = next(model.parameters()).device
        self.background = background.to(self.device, torch.float32)
        self.skip_color_dist = float(skip_color_dist)
        self.max_angle = float(max_angle)
        self.chunk_pixels = check_chunk_pixels(chunk_pixels)
        h, w = self.background.shape[:2]
        self.grid = pixel_grid(h, w, self.device).reshape(h * w, 2)
        with torch.no_grad():
            feats = pixel_features(self.background[None])
            self.bg_slopes = self._slopes(feats.reshape(-1, 5))

    def _slopes(self, feats: torch.Tensor) -> torch.Tensor:
        """``(N, 5)`` features -> ``(N, 2)`` slopes, ``chunk_pixels`` rows at a time."""
        rows = self.chunk_pixels if self.device.type == "cpu" else 0
        return mlp_rows(self.model.layers, feats, rows).clamp_(-self.max_angle, self.max_angle).tan_()

    @torch.no_grad()
    def __call__(self, bgr: torch.Tensor, changed: torch.Tensor | None = None) -> torch.Tensor:
        """``(B, H, W, 3)`` BGR (a tensor or a numpy array) -> ``(B, H, W, 2)`` gradients
        ``(dh/dx, dh/dy)``.

        ``changed`` (``(B, H, W)`` bool) restricts evaluation to those pixels; by
        default it is derived from the colour distance to the background.
        """
        bgr = as_tensor(bgr, "image batch")
        if bgr.ndim != 4 or bgr.shape[1:] != self.background.shape:
            raise ValueError(
                f"image batch must be (B, {', '.join(map(str, self.background.shape))}), "
                f"got {tuple(bgr.shape)}"
            )
        bgr = bgr.to(self.device)
        b, h, w, _ = bgr.shape
        if changed is None and self.skip_color_dist > 0:
            changed = dilate(colour_distance(bgr, self.background) > self.skip_color_dist, 5)
        if changed is None:
            out = self._slopes(pixel_features(bgr).reshape(-1, 5)).reshape(b, h, w, 2)
            return out - self.bg_slopes.reshape(h, w, 2)
        flat = torch.nonzero(changed.reshape(-1)).squeeze(1)  # (N,) indices into B*H*W
        pix = flat if b == 1 else flat % (h * w)
        colour = bgr.reshape(-1, 3).index_select(0, flat).float().div_(255.0)
        feats = torch.cat([colour, self.grid.index_select(0, pix)], dim=1)
        slopes = self._slopes(feats).sub_(self.bg_slopes.index_select(0, pix))
        return torch.zeros(b * h * w, 2, device=self.device).index_copy_(0, flat, slopes).reshape(b, h, w, 2)
