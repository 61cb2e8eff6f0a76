"""The ``Frame`` batch type and the builder that computes it (method.md section 3).

A :class:`Frame` always carries a leading batch dimension ``B`` (a single frame is
``B = 1``); ``frame[i]`` slices one element. Maps are float32 on the builder's device.
"""

from __future__ import annotations

from dataclasses import dataclass, fields, replace

import torch

from tactile_slam.calibration.model import GradientDecoder
from tactile_slam.config import Config
from tactile_slam.geometry.contact import colour_distance, colour_mask, contact_mask, zero_level
from tactile_slam.geometry.curvature import curvature, normals_from_gradients
from tactile_slam.geometry.morphology import dilate
from tactile_slam.geometry.poisson import integrate_exact, integrate_legacy


class InputError(ValueError):
    """An input frame or sequence is unusable (wrong size, NaN, empty, ...)."""


@dataclass
class Frame:
    """Geometry of ``B`` tactile frames.

    Attributes:
        gradients: ``(B, H, W, 2)`` slopes ``(dh/dx, dh/dy)``, px/px; ``None`` in a
            stored keyframe (:meth:`clone` with ``gradients=False``): nothing after the
            frame's construction reads them, and they are a quarter of its memory.
        height: ``(B, H, W)`` px; the undeformed gel is 0 and pressing is negative.
        contact: ``(B, H, W)`` bool, the eroded contact mask used by every later stage.
        normals: ``(B, H, W, 3)`` gel-surface unit normals (toward the object).
        curvature: ``(B, H, W)`` 1/px, zero outside contact, clipped.
        in_contact: ``(B,)`` bool, eroded contact area above the configured minimum.
        index: ``(B,)`` int64 video index (``-1`` if unknown).
        timestamp: ``(B,)`` float64 seconds (``nan`` if unknown).
        mm_per_px: sensor scale.
    """

    gradients: torch.Tensor | None
    height: torch.Tensor
    contact: torch.Tensor
    normals: torch.Tensor
    curvature: torch.Tensor
    in_contact: torch.Tensor
    index: torch.Tensor
    timestamp: torch.Tensor
    mm_per_px: float

    def __len__(self) -> int:
        return self.height.shape[0]

    @property
    def shape(self) -> tuple[int, int]:
        return tuple(self.height.shape[1:3])

    @property
    def device(self) -> torch.device:
        return self.height.device

    def _map(self, fn) -> "Frame":
        """``fn`` applied to every tensor (absent gradients stay ``None``)."""
        kw = {f.name: getattr(self, f.name) for f in fields(self) if f.name != "mm_per_px"}
        return replace(self, **{k: None if v is None else fn(v) for k, v in kw.items()})

    def __getitem__(self, i: int | slice | torch.Tensor) -> "Frame":
        if isinstance(i, int):
            i = slice(i, i + 1) if i != -1 else slice(-1, None)
        return self._map(lambda t: t[i])

    def clone(self, gradients: bool = True) -> "Frame":
        """The frames with maps of their own. ``frames[i]`` is a view that keeps the whole
        batch's storage alive (about 2.2 MB per 320x240 frame); a record that outlives
        its batch, such as a keyframe, stores a clone, without the gradients if
        ``gradients`` is False (0.6 of the 2.2 MB)."""
        return replace(self._map(torch.clone), **({} if gradients else {"gradients": None}))

    def to(self, device: torch.device | str) -> "Frame":
        return self._map(lambda t: t.to(device))

    @staticmethod
    def cat(frames: list["Frame"]) -> "Frame":
        """One batch of ``frames``; its gradients are ``None`` if any frame has none."""
        if not frames:
            raise InputError("cannot concatenate an empty list of frames")
        kw = {}
        for f in fields(Frame):
            if f.name != "mm_per_px":
                parts = [getattr(fr, f.name) for fr in frames]
                kw[f.name] = None if any(p is None for p in parts) else torch.cat(parts)
        return Frame(mm_per_px=frames[0].mm_per_px, **kw)


def check_images(bgr: torch.Tensor, shape: tuple[int, int]) -> None:
    """Raise :class:`InputError` unless ``bgr`` is ``(B, H, W, 3)`` finite."""
    h, w = shape
    if bgr.ndim != 4 or tuple(bgr.shape[1:]) != (h, w, 3):
        raise InputError(f"expected BGR images of shape (B, {h}, {w}, 3), got {tuple(bgr.shape)}")
    if bgr.shape[0] == 0:
        raise InputError("empty image batch")
    if bgr.is_floating_point() and not torch.isfinite(bgr).all():
        raise InputError("image contains NaN or Inf values")


def check_gradients(gradients: torch.Tensor, shape: tuple[int, int] | None = None) -> None:
    """Raise :class:`InputError` unless ``gradients`` is ``(B, H, W, 2)`` finite."""
    if gradients.ndim != 4 or gradients.shape[-1] != 2:
        raise InputError(f"expected gradients of shape (B, H, W, 2), got {tuple(gradients.shape)}")
    if shape is not None and tuple(gradients.shape[1:3]) != tuple(shape):
        raise InputError(f"expected gradient maps of size {shape}, got {tuple(gradients.shape[1:3])}")
    if gradients.shape[0] == 0:
        raise InputError("empty gradient batch")
    if not torch.isfinite(gradients).all():
        raise InputError("gradients contain NaN or Inf values")


class FrameBuilder:
    """Computes :class:`Frame` batches from BGR images or from gradient maps.

    Args:
        config: sensor, contact and curvature settings.
        decoder: colour-to-gradient decoder (with its background); required only for
            :meth:`from_bgr`. Gradient-level input never touches the model.
        integrator: ``"exact"`` (default) or ``"legacy"`` (public SDK, for comparison).
    """

    def __init__(self, config: Config, decoder: GradientDecoder | None = None, integrator: str = "exact"):
        if integrator not in ("exact", "legacy"):
            raise ValueError(f"integrator must be 'exact' or 'legacy', got {integrator!r}")
        self.depth_test = config.depth_test  # (threshold px, fraction, floor px); checked here, not at the first frame
        self.config = config
        self.decoder = decoder
        self.integrate = integrate_exact if integrator == "exact" else integrate_legacy

    @property
    def device(self) -> torch.device:
        return self.decoder.device if self.decoder is not None else torch.device("cpu")

    def from_bgr(
        self,
        bgr: torch.Tensor,
        index: torch.Tensor | None = None,
        timestamp: torch.Tensor | None = None,
    ) -> Frame:
        """``(B, H, W, 3)`` uint8/float BGR -> :class:`Frame`."""
        if self.decoder is None:
            raise InputError("FrameBuilder.from_bgr needs a calibration model and background")
        cfg = self.config
        check_images(bgr, cfg.sensor.shape)
        bgr = bgr.to(self.decoder.device)
        dist = colour_distance(bgr, self.decoder.background)
        skip = cfg.contact.mlp_skip_color_dist
        changed = dilate(dist > skip, 5) if skip > 0 else None
        gradients = self.decoder(bgr, changed=changed)
        colour = colour_mask(
            dist, cfg.contact.color_dist_threshold, cfg.contact.dilate, cfg.contact.erode, cfg.contact.fill_holes
        )
        return self._finish(gradients, colour, dilate(colour, cfg.contact.dilate), None, index, timestamp)

    def from_gradients(
        self,
        gradients: torch.Tensor,
        contact: torch.Tensor | None = None,
        index: torch.Tensor | None = None,
        timestamp: torch.Tensor | None = None,
    ) -> Frame:
        """``(B, H, W, 2)`` gradients (+ optional ``(B, H, W)`` contact masks, used
        as the final eroded mask as-is) -> :class:`Frame`. Without masks the contact
        comes from the height rule alone."""
        check_gradients(gradients, self.config.sensor.shape)
        if contact is not None and tuple(contact.shape) != tuple(gradients.shape[:3]):
            raise InputError(
                f"contact masks {tuple(contact.shape)} do not match gradients {tuple(gradients.shape[:3])}"
            )
        gradients = gradients.to(self.device, torch.float32)
        if contact is not None:
            contact = contact.to(self.device).bool()
        changed = contact if contact is not None else torch.zeros(gradients.shape[:3], dtype=torch.bool, device=gradients.device)
        return self._finish(gradients, None, dilate(changed, self.config.contact.dilate), contact, index, timestamp)

    def _finish(self, gradients, colour, changed, given_contact, index, timestamp) -> Frame:
        cfg = self.config
        b = gradients.shape[0]
        height = zero_level(self.integrate(gradients), changed)
        if given_contact is None:
            threshold, fraction, floor = self.depth_test
            _, contact = contact_mask(height, colour, threshold, cfg.contact.height_percentile, cfg.final_erode_px,
                                      fraction, floor)
        else:
            contact = given_contact
        lap = curvature(gradients, contact, cfg.curvature.blur_ksize, cfg.curvature.blur_sigma, cfg.curvature.clip)
        in_contact = contact.reshape(b, -1).sum(dim=1) >= cfg.min_contact_px
        if index is None:
            index = torch.full((b,), -1, dtype=torch.int64)
        if timestamp is None:
            timestamp = torch.full((b,), float("nan"), dtype=torch.float64)
        return Frame(
            gradients=gradients,
            height=height,
            contact=contact,
            normals=normals_from_gradients(gradients),
            curvature=lap,
            in_contact=in_contact,
            index=torch.as_tensor(index, dtype=torch.int64, device=gradients.device).reshape(b),
            timestamp=torch.as_tensor(timestamp, dtype=torch.float64, device=gradients.device).reshape(b),
            mm_per_px=cfg.sensor.mm_per_px,
        )
