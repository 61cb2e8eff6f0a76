"""The ``Frame`` batch type and the builder that computes it (method.md section 3).

A :class:`Frame` always carries a leading batch dimension ``B`` (a single frame is
``B = 1``); ``frame[i]`` slices one element. Maps are float32 on the builder's device.
"""

from __future__ import annotations

from dataclasses import dataclass, fields, replace
from typing import TYPE_CHECKING

import numpy as np
import torch

from tactile_slam.config import Config
from tactile_slam.geometry.contact import colour_distance, colour_mask, contact_mask, gel_visible, zero_level
from tactile_slam.geometry.curvature import curvature, normals_from_gradients
from tactile_slam.geometry.morphology import dilate, mask_bounds, window_around
from tactile_slam.geometry.poisson import integrate_exact, integrate_legacy

if TYPE_CHECKING:  # the decoder's module reads its inputs with as_tensor below
    from tactile_slam.calibration.model import GradientDecoder


class InputError(ValueError):
    """An input frame or sequence is unusable (wrong size, NaN, empty, ...)."""


_SCALARS = ("mm_per_px", "decoded")  # Frame's fields that are not per-frame tensors


def item_slice(i: int, n: int) -> slice:
    """The one-item slice a batch's integer index ``i`` (negative from the end) selects,
    so that the item keeps its batch axis. Raises ``IndexError`` outside ``[-n, n)``,
    which also ends a ``for`` loop over the batch."""
    if not -n <= i < n:
        raise IndexError(f"index {i} is out of range for a batch of {n}")
    i %= n
    return slice(i, i + 1)


@dataclass
class Frame:
    """Geometry of ``B`` tactile frames.

    Attributes:
        gradients: ``(B, H, W, 2)`` slopes ``(dh/dx, dh/dy)``, px/px; ``None`` in a
            stored keyframe (:meth:`CroppedFrame.expand`): nothing after the frame's
            construction reads them.
        height: ``(B, H, W)`` px; the undeformed gel is 0 and pressing is negative.
        contact: ``(B, H, W)`` bool, the eroded contact mask used by every later stage.
        normals: ``(B, H, W, 3)`` gel-surface unit normals (toward the object).
        curvature: ``(B, H, W)`` 1/px, zero outside contact, clipped.
        in_contact: ``(B,)`` bool, eroded contact area above the configured minimum.
        depth_known: ``(B,)`` bool, enough undeformed gel in view to fix the height zero
            (:func:`~tactile_slam.geometry.contact.gel_visible`); where False the heights,
            and so the press depth and every z translation measured from them, are a guess.
        index: ``(B,)`` int64 video index (``-1`` if unknown).
        timestamp: ``(B,)`` float64 seconds (``nan`` if unknown).
        mm_per_px: sensor scale.
        decoded: whether the gradients were decoded from images by a calibration model
            (:meth:`FrameBuilder.from_bgr`), and so carry its flattening of steep slopes
            (docs/calibration.md, "Gain by slope"); False for gradients given as input.
    """

    gradients: torch.Tensor | None
    height: torch.Tensor
    contact: torch.Tensor
    normals: torch.Tensor
    curvature: torch.Tensor
    in_contact: torch.Tensor
    depth_known: torch.Tensor
    index: torch.Tensor
    timestamp: torch.Tensor
    mm_per_px: float
    decoded: bool = False

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
        kw = {f.name: getattr(self, f.name) for f in fields(self) if f.name not in _SCALARS}
        return replace(self, **{k: None if v is None else fn(v) for k, v in kw.items()})

    def __getitem__(self, i: int | slice | torch.Tensor) -> "Frame":
        if isinstance(i, int):
            i = item_slice(i, len(self))
        return self._map(lambda t: t[i])

    def clone(self) -> "Frame":
        """The frames with maps of their own. ``frames[i]`` is a view that keeps the whole
        batch's storage alive (about 2.2 MB per 320x240 frame); a record that outlives its
        batch stores a clone, or a :class:`CroppedFrame`."""
        return self._map(torch.clone)

    def to(self, device: torch.device | str) -> "Frame":
        return self._map(lambda t: t.to(device))

    @staticmethod
    def cat(frames: list["Frame"]) -> "Frame":
        """One batch of ``frames``; its gradients are ``None`` if any frame has none, and it
        is :attr:`decoded` if any frame is."""
        if not frames:
            raise InputError("cannot concatenate an empty list of frames")
        kw = {}
        for f in fields(Frame):
            if f.name not in _SCALARS:
                parts = [getattr(fr, f.name) for fr in frames]
                kw[f.name] = None if any(p is None for p in parts) else torch.cat(parts)
        return Frame(mm_per_px=frames[0].mm_per_px, decoded=any(fr.decoded for fr in frames), **kw)


@dataclass
class CroppedFrame:
    """One frame's maps inside a box around its contact (``B = 1``), for a record that
    outlives its batch (a keyframe): contact covers a few percent to a third of a
    touch's image, so the box holds a fraction of the full maps. Outside the box the
    gel counts as flat and undeformed: height 0, normal ``(0, 0, 1)``, curvature 0,
    no contact (:meth:`expand`). The box keeps ``margin`` pixels around the contact
    (:func:`crop_to_contact`), more than any stage reads beyond a contact pixel
    (bilinear sampling 1, Sobel and curvature stencils 2), so what those stages compute
    is unchanged; the full maps outside that margin are not kept.

    Attributes:
        box: the maps inside the box, a :class:`Frame` with ``B = 1`` of size ``(h, w)``
            and no gradients (its ``index``, ``timestamp`` and ``in_contact`` are the
            frame's).
        top, left: the box's first row and column in the full image.
        full_shape: the full image's ``(H, W)``.
    """

    box: Frame
    top: int
    left: int
    full_shape: tuple[int, int]

    def __len__(self) -> int:
        return 1

    @property
    def shape(self) -> tuple[int, int]:
        """The full image's ``(H, W)``, as :attr:`Frame.shape`."""
        return tuple(self.full_shape)

    @property
    def device(self) -> torch.device:
        return self.box.device

    @property
    def mm_per_px(self) -> float:
        return self.box.mm_per_px

    @property
    def decoded(self) -> bool:
        return self.box.decoded

    def expand(self) -> Frame:
        """The full-size :class:`Frame` (new tensors; gradients ``None``)."""
        return full_batch([self])


def full_batch(parts: list[Frame | CroppedFrame]) -> Frame:
    """One full-size batch of frames and cropped frames, in order, each crop pasted
    straight into it (no full-size copy of its own); gradients ``None`` unless every
    part is a :class:`Frame` with gradients (then this is :meth:`Frame.cat`)."""
    if not parts:
        raise InputError("cannot build a batch from an empty list of frames")
    if all(isinstance(p, Frame) for p in parts):
        return Frame.cat(parts)
    shape = _common_shape(parts)
    return _paste(parts, shape, torch.zeros((sum(len(p) for p in parts), 2), dtype=torch.int64))


@dataclass
class WindowBatch:
    """``B`` frames' maps inside windows of one size ``(h, w)``, each at its own place in
    the full image (:func:`window_batch`): what a batched registration reads of targets
    whose contact covers a fraction of the image. As in :class:`CroppedFrame`, a frame is
    flat and undeformed outside its window.

    Attributes:
        maps: the windows, a :class:`Frame` of size ``(h, w)`` without gradients.
        origins: ``(B, 2)`` int64 on the CPU, each window's first row and column in the
            full image.
        full_shape: the full image's ``(H, W)``.
    """

    maps: Frame
    origins: torch.Tensor
    full_shape: tuple[int, int]

    def __len__(self) -> int:
        return len(self.maps)

    @property
    def shape(self) -> tuple[int, int]:
        """The full image's ``(H, W)``, as :attr:`Frame.shape`."""
        return tuple(self.full_shape)

    @property
    def device(self) -> torch.device:
        return self.maps.device

    @property
    def mm_per_px(self) -> float:
        return self.maps.mm_per_px

    def __getitem__(self, i: int | slice | torch.Tensor) -> "WindowBatch":
        if isinstance(i, int):
            i = item_slice(i, len(self))
        return WindowBatch(self.maps[i], self.origins[i.cpu() if isinstance(i, torch.Tensor) else i],
                           self.full_shape)

    def to(self, device: torch.device | str) -> "WindowBatch":
        return WindowBatch(self.maps.to(device), self.origins, self.full_shape)

    def expand(self) -> Frame:
        """The full-size :class:`Frame` (new tensors; gradients ``None``)."""
        return _paste([self.maps], self.full_shape, -self.origins)


def window_batch(parts: list[Frame | CroppedFrame], multiple: int = 1) -> WindowBatch:
    """Frames and cropped frames, in order, in windows of one size.

    A cropped frame's window is its box grown by ``multiple`` pixels on every side with
    its edges at multiples of ``multiple`` (clipped to the image); a full frame's is the
    whole image. All windows take the largest height and width, and a window that would
    then pass the image's far edge is moved back inside it. So maps averaged over
    ``f x f`` blocks, for any ``f`` dividing ``multiple``, are the full maps' blocks, and
    the blocks next to any block of a box are in its window too. Windows are at least
    2 x 2 px (a crop without contact has an empty box).

    Args:
        parts: frames of one size ``(H, W)``; ``H`` and ``W`` must be multiples of
            ``multiple``.
        multiple: window alignment (>= 1), e.g. the lcm of a registration's coarse factors.

    Returns:
        a :class:`WindowBatch` of ``sum(len(p))`` frames (gradients are not kept).
    """
    if not parts:
        raise InputError("cannot build a batch from an empty list of frames")
    h, w = _common_shape(parts)
    m = int(multiple)
    if m < 1 or h % m or w % m:
        raise InputError(f"window alignment must be >= 1 and divide the image size {(h, w)}, got {multiple}")
    spans = []  # (first row, end row, first column, end column) wanted
    for p in parts:
        if isinstance(p, CroppedFrame):
            bh, bw = p.box.shape
            rows, cols = window_around((p.top, p.top + bh - 1, p.left, p.left + bw - 1), m, (h, w))
            spans.append((rows.start // m * m, -(-rows.stop // m) * m, cols.start // m * m, -(-cols.stop // m) * m))
        else:
            spans += [(0, h, 0, w)] * len(p)
    span = torch.tensor(spans, dtype=torch.int64)
    # at least 2 px (an empty box at alignment 1 would give 1, where grid coordinates are undefined)
    size = (max(int((span[:, 1] - span[:, 0]).max()), 2), max(int((span[:, 3] - span[:, 2]).max()), 2))
    origins = torch.stack([span[:, 0].clamp_max(h - size[0]), span[:, 2].clamp_max(w - size[1])], 1)
    return WindowBatch(_paste(parts, size, origins), origins, (h, w))


def _common_shape(parts: list[Frame | CroppedFrame]) -> tuple[int, int]:
    """The full size ``(H, W)`` shared by every part; :class:`InputError` otherwise."""
    shape = tuple(parts[0].shape)
    for p in parts:
        if tuple(p.shape) != shape:
            raise InputError(f"frames of different sizes in one batch: {tuple(p.shape)} and {shape}")
    return shape


def _paste(parts: list[Frame | CroppedFrame], size: tuple[int, int], origins: torch.Tensor) -> Frame:
    """The parts' frames in windows of ``size`` ``(h, w)`` whose first row and column in
    the full image are ``origins`` ``(n, 2)`` (negative: the part's own window starts
    there inside the output), flat and undeformed where a part has no maps. A part's
    maps must lie inside its window. Gradients ``None``."""
    n, (h, w) = len(origins), size
    maps = [p.box if isinstance(p, CroppedFrame) else p for p in parts]
    first, dev = maps[0], parts[0].device
    out = Frame(gradients=None, height=torch.zeros((n, h, w), dtype=first.height.dtype, device=dev),
                contact=torch.zeros((n, h, w), dtype=torch.bool, device=dev),
                normals=torch.zeros((n, h, w, 3), dtype=first.normals.dtype, device=dev),
                curvature=torch.zeros((n, h, w), dtype=first.curvature.dtype, device=dev),
                in_contact=torch.cat([m.in_contact for m in maps]),
                depth_known=torch.cat([m.depth_known for m in maps]), index=torch.cat([m.index for m in maps]),
                timestamp=torch.cat([m.timestamp for m in maps]), mm_per_px=first.mm_per_px,
                decoded=any(m.decoded for m in maps))
    out.normals[..., 2] = 1.0
    i = 0
    for p, mp in zip(parts, maps):
        top, left = (p.top, p.left) if isinstance(p, CroppedFrame) else (0, 0)
        mh, mw = mp.shape
        for j in range(len(mp)):
            r, c = top - int(origins[i + j, 0]), left - int(origins[i + j, 1])
            for name in ("height", "contact", "normals", "curvature"):
                getattr(out, name)[i + j, r:r + mh, c:c + mw] = getattr(mp, name)[j]
        i += len(mp)
    return out


def contact_bounds(part: Frame | CroppedFrame) -> tuple[int, int, int, int] | None:
    """Inclusive ``(row_min, row_max, col_min, col_max)`` of one frame's contact in
    full-image pixels (a cropped frame is not expanded), or ``None`` without contact."""
    if len(part) != 1:
        raise InputError(f"contact bounds are read from one frame (B = 1), got B = {len(part)}")
    maps, top, left = (part.box, part.top, part.left) if isinstance(part, CroppedFrame) else (part, 0, 0)
    box = mask_bounds(maps.contact[0])
    if box is None:
        return None
    r0, r1, c0, c1 = box
    return r0 + top, r1 - 1 + top, c0 + left, c1 - 1 + left


def height_and_contact_in(part: Frame | CroppedFrame, rows: slice, cols: slice) -> tuple[torch.Tensor, torch.Tensor]:
    """Height (px) and contact of one frame over a window of the full image, reading
    flat gel (height 0, no contact) outside a cropped frame's box, as its
    :meth:`~CroppedFrame.expand` would, without expanding it.

    Args:
        part: a :class:`Frame` with ``B = 1`` or a :class:`CroppedFrame`.
        rows, cols: the window, slices of the full image with ``0 <= start < stop``
            within it.

    Returns:
        ``(h, w)`` height and ``(h, w)`` bool contact (views of a full frame's maps).
    """
    if len(part) != 1:
        raise InputError(f"a window is read from one frame (B = 1), got B = {len(part)}")
    for s, n, name in ((rows, part.shape[0], "rows"), (cols, part.shape[1], "columns")):
        if s.start is None or s.stop is None or s.step not in (None, 1) or not 0 <= s.start < s.stop <= n:
            raise InputError(f"window {name} {s} must be a non-empty slice within 0..{n}")
    if isinstance(part, Frame):
        return part.height[0, rows, cols], part.contact[0, rows, cols]
    box = part.box
    height = torch.zeros((rows.stop - rows.start, cols.stop - cols.start), dtype=box.height.dtype, device=box.device)
    contact = torch.zeros(height.shape, dtype=torch.bool, device=box.device)
    bh, bw = box.shape
    r0, r1 = max(rows.start, part.top), min(rows.stop, part.top + bh)
    c0, c1 = max(cols.start, part.left), min(cols.stop, part.left + bw)
    if r0 < r1 and c0 < c1:
        dst = (slice(r0 - rows.start, r1 - rows.start), slice(c0 - cols.start, c1 - cols.start))
        src = (0, slice(r0 - part.top, r1 - part.top), slice(c0 - part.left, c1 - part.left))
        height[dst], contact[dst] = box.height[src], box.contact[src]
    return height, contact


def own_maps(frame: Frame) -> Frame:
    """A copy of ``frame``'s maps without its gradients, for a record that outlives its
    batch (``frames[i]`` is a view that keeps the whole batch alive); nothing after a
    frame's construction reads its gradients."""
    return replace(frame, gradients=None).clone()


def crop_to_contact(frame: Frame, margin: int = 8) -> CroppedFrame:
    """Copy one frame's maps (``B = 1``) within ``margin`` pixels of its contact's
    bounding box (clipped to the image). A frame without contact keeps an empty box.

    Args:
        frame: a :class:`Frame` with ``B = 1``.
        margin: pixels kept around the contact box (>= 3: see :class:`CroppedFrame`).

    Returns:
        a :class:`CroppedFrame` with maps of its own (gradients are not kept).
    """
    if len(frame) != 1:
        raise InputError(f"crop_to_contact takes one frame (B = 1), got B = {len(frame)}")
    if margin < 3:
        raise InputError(f"crop margin must be >= 3 px (the widest stencil that reads past the contact), got {margin}")
    bounds = contact_bounds(frame)
    rows, cols = (slice(0, 0), slice(0, 0)) if bounds is None else window_around(bounds, margin, frame.shape)
    r0, r1, c0, c1 = rows.start, rows.stop, cols.start, cols.stop
    box = own_maps(replace(frame, height=frame.height[:, r0:r1, c0:c1], contact=frame.contact[:, r0:r1, c0:c1],
                           normals=frame.normals[:, r0:r1, c0:c1], curvature=frame.curvature[:, r0:r1, c0:c1]))
    return CroppedFrame(box=box, top=r0, left=c0, full_shape=tuple(frame.shape))


def as_tensor(x, what: str) -> torch.Tensor:
    """A torch tensor, or a numpy array (e.g. an OpenCV image) as one without a copy where
    its layout allows; anything else is an :class:`InputError` naming ``what``."""
    if isinstance(x, torch.Tensor):
        return x
    if isinstance(x, np.ndarray):
        return torch.from_numpy(np.ascontiguousarray(x))
    raise InputError(f"{what} must be a torch tensor or a numpy array, got {type(x).__name__}")


def _batch_hint(x: torch.Tensor, item: tuple[int, ...]) -> str:
    """A hint when ``x`` is one item without its batch axis."""
    return "; for one frame add a batch axis (x[None])" if tuple(x.shape) == item else ""


def check_images(bgr: torch.Tensor, shape: tuple[int, int]) -> None:
    """Raise :class:`InputError` unless ``bgr`` is ``(B, H, W, 3)`` finite."""
    h, w = shape
    if bgr.ndim != 4 or tuple(bgr.shape[1:]) != (h, w, 3):
        raise InputError(f"expected BGR images of shape (B, {h}, {w}, 3), got {tuple(bgr.shape)}"
                         + _batch_hint(bgr, (h, w, 3)))
    if bgr.shape[0] == 0:
        raise InputError("empty image batch")
    if bgr.is_floating_point() and not torch.isfinite(bgr).all():
        raise InputError("image contains NaN or Inf values")


def check_gradients(gradients: torch.Tensor, shape: tuple[int, int] | None = None) -> None:
    """Raise :class:`InputError` unless ``gradients`` is ``(B, H, W, 2)`` finite."""
    if gradients.ndim != 4 or gradients.shape[-1] != 2:
        raise InputError(f"expected gradients of shape (B, H, W, 2), got {tuple(gradients.shape)}"
                         + (_batch_hint(gradients, (*shape, 2)) if shape is not None else ""))
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
        device: where gradient-level frames are computed (default CPU). Image-level frames
            are computed on the decoder's device; a ``device`` that differs from it is refused.
    """

    def __init__(self, config: Config, decoder: GradientDecoder | None = None, integrator: str = "exact",
                 device: str | torch.device | None = None):
        if integrator not in ("exact", "legacy"):
            raise ValueError(f"integrator must be 'exact' or 'legacy', got {integrator!r}")
        if device is not None and decoder is not None and torch.device(device) != decoder.device:
            raise ValueError(f"FrameBuilder device {torch.device(device)} differs from its decoder's "
                             f"{decoder.device}: move the model (load_model(path, device))")
        self.depth_test = config.depth_test  # (threshold px, fraction, floor px); checked here, not at the first frame
        self.config = config
        self.decoder = decoder
        self.integrate = integrate_exact if integrator == "exact" else integrate_legacy
        self._device = torch.device(device) if device is not None else torch.device("cpu")

    @property
    def device(self) -> torch.device:
        """Where frames are computed: the decoder's device, else the one given (CPU by default)."""
        return self.decoder.device if self.decoder is not None else self._device

    def from_bgr(
        self,
        bgr: torch.Tensor,
        index: torch.Tensor | None = None,
        timestamp: torch.Tensor | None = None,
    ) -> Frame:
        """``(B, H, W, 3)`` uint8/float BGR (a tensor, or a numpy array such as OpenCV's
        frames) -> :class:`Frame`."""
        if self.decoder is None:
            raise InputError("FrameBuilder.from_bgr needs a calibration model and background")
        cfg = self.config
        bgr = as_tensor(bgr, "BGR images")
        check_images(bgr, cfg.sensor.shape)
        bgr = bgr.to(self.decoder.device)
        dist = colour_distance(bgr, self.decoder.background)
        skip = cfg.contact.mlp_skip_color_dist
        changed = dilate(dist > skip, 5) if skip > 0 else None
        gradients = self.decoder(bgr, changed=changed)
        colour = colour_mask(
            dist, cfg.contact.color_dist_threshold, cfg.contact.dilate, cfg.contact.erode, cfg.contact.fill_holes
        )
        return replace(self._finish(gradients, colour, dilate(colour, cfg.contact.dilate), None, index, timestamp),
                       decoded=True)

    def from_gradients(
        self,
        gradients: torch.Tensor,
        contact: torch.Tensor | None = None,
        index: torch.Tensor | None = None,
        timestamp: torch.Tensor | None = None,
    ) -> Frame:
        """``(B, H, W, 2)`` gradients (+ optional ``(B, H, W)`` contact masks: the final
        eroded mask as-is, or with ``contact.given_masks: region`` the region the height
        rule and final erosion apply in, like an image's colour mask) -> :class:`Frame`;
        tensors or numpy arrays. Without masks the contact comes from the height rule alone."""
        gradients = as_tensor(gradients, "gradients")
        contact = None if contact is None else as_tensor(contact, "contact masks")
        check_gradients(gradients, self.config.sensor.shape)
        if contact is not None and tuple(contact.shape) != tuple(gradients.shape[:3]):
            raise InputError(
                f"contact masks {tuple(contact.shape)} do not match gradients {tuple(gradients.shape[:3])}"
            )
        gradients = gradients.to(self.device, torch.float32)
        if contact is not None:
            if contact.is_floating_point():  # integer masks (0/1, 0/255) count nonzero as contact
                stray = contact[(contact != 0) & (contact != 1)]  # NaN or fractions: not a mask
                if stray.numel():
                    raise InputError(f"float contact masks must be 0 or 1, got values such as {stray[0].item()}")
            contact = contact.to(self.device).bool()
        changed = contact if contact is not None else torch.zeros(gradients.shape[:3], dtype=torch.bool,
                                                                  device=gradients.device)
        changed = dilate(changed, self.config.contact.dilate)
        if self.config.contact.given_masks == "region":
            return self._finish(gradients, contact, changed, None, index, timestamp)
        return self._finish(gradients, None, changed, contact, index, timestamp)

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
            depth_known=gel_visible(changed),
            index=torch.as_tensor(index, dtype=torch.int64, device=gradients.device).reshape(b),
            timestamp=torch.as_tensor(timestamp, dtype=torch.float64, device=gradients.device).reshape(b),
            mm_per_px=cfg.sensor.mm_per_px,
        )
