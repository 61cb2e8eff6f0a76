import math
from dataclasses import replace

import numpy as np
import pytest
from scipy import ndimage
import torch

from tactile_slam.calibration.model import GradientDecoder, GradientMLP, load_model
from tactile_slam.config import Config
from tactile_slam.geometry.frame import (Frame, FrameBuilder, InputError, crop_to_contact, full_batch, window_batch,
                                         contact_bounds, height_and_contact_in, window_around)

from . import presses
from .surfaces import central_gradients, spherical_cap


def _ball_frame(builder, depth=12.0, cc=0.0):
    h = spherical_cap(49.76, depth, cc=cc)
    g = central_gradients(h).float()
    return builder.from_gradients(g), h


class TestFromGradients:
    def test_ball_height_and_contact(self):
        fb = FrameBuilder(Config())
        f, h = _ball_frame(fb)
        assert isinstance(f, Frame) and len(f) == 1
        # height: gel at zero, ball bottom at -depth (2%)
        assert abs(float(f.height.min()) + 12.0) < 0.24
        assert abs(float(f.height[0, 0, 0])) < 0.05
        # contact: the height rule selects the pressed disc, then a 5x5 erosion with a
        # non-contact border (scipy as the independent implementation)
        true = ndimage.binary_erosion((h < -3.155).numpy(), np.ones((5, 5)), border_value=0)
        c = f.contact[0].numpy()
        iou = (c & true).sum() / (c | true).sum()
        assert iou > 0.95
        assert bool(f.in_contact[0])

    def test_frames_are_computed_on_the_builders_device(self, device):
        """Gradient-level frames follow the builder's ``device`` whatever the input's (the
        pipeline's ``--device`` for gradient sequences), with the same maps as on the CPU."""
        fb = FrameBuilder(Config(), device=device)
        assert fb.device == device
        f, _ = _ball_frame(fb)
        assert f.normals.device.type == f.height.device.type == f.contact.device.type == device.type
        cpu, _ = _ball_frame(FrameBuilder(Config()))
        torch.testing.assert_close(f.height.cpu(), cpu.height, rtol=0, atol=1e-4)
        assert torch.equal(f.contact.cpu(), cpu.contact)

    def test_a_device_other_than_the_decoders_is_refused(self):
        decoder = GradientDecoder(GradientMLP(), torch.zeros(240, 320, 3))  # on the CPU
        with pytest.raises(ValueError, match="differs from its decoder"):
            FrameBuilder(Config(), decoder, device="meta")

    def test_no_contact_on_flat_gel(self):
        fb = FrameBuilder(Config())
        f = fb.from_gradients(torch.zeros(1, 240, 320, 2))
        assert not f.in_contact[0] and f.contact.sum() == 0 and (f.curvature == 0).all()

    def test_given_masks_used_as_is(self):
        fb = FrameBuilder(Config())
        g = central_gradients(spherical_cap()).float()
        m = torch.zeros(1, 240, 320, dtype=torch.bool)
        m[0, 100:140, 140:180] = True
        f = fb.from_gradients(g, contact=m)
        assert torch.equal(f.contact, m)

    def test_given_masks_as_region_get_the_depth_rule(self):
        """``contact.given_masks: region``: a given mask bounds the contact like an image's
        colour mask; the depth test and the final erosion apply inside it."""
        cfg = Config()
        cfg.contact.given_masks = "region"
        fb = FrameBuilder(cfg)
        h = spherical_cap(49.76, 12.0)
        g = central_gradients(h).float()
        everywhere = torch.ones(1, 240, 320, dtype=torch.bool)
        assert torch.equal(fb.from_gradients(g, contact=everywhere).contact, fb.from_gradients(g).contact)
        left = torch.zeros(1, 240, 320, dtype=torch.bool)
        left[..., :160] = True
        deep = (h < -0.2 / 0.0634).numpy() & left.numpy()  # a deep press keeps the fixed 0.2 mm rule
        true = ndimage.binary_erosion(deep[0], np.ones((5, 5)), border_value=0)
        assert np.array_equal(fb.from_gradients(g, contact=left).contact[0].numpy(), true)

    def test_given_loose_mask_as_region_drops_the_shallow_rim(self):
        """A mask of everything pressed 0.03 mm (a simulator's physical contact) keeps, as a
        region, only the part deeper than half the touch's depth."""
        cfg = Config()
        h = spherical_cap(49.76, 3.0)  # 0.19 mm deep: the relative rule applies
        g = central_gradients(h).float()
        loose = (h < -0.03 / 0.0634)[None]
        assert torch.equal(FrameBuilder(cfg).from_gradients(g, contact=loose).contact, loose)
        cfg.contact.given_masks = "region"
        c = FrameBuilder(cfg).from_gradients(g, contact=loose).contact
        assert c.any() and not (c & ~loose).any()
        assert float(h[None][c].max()) < -0.45 * 3.0 and int(c.sum()) < 0.6 * int(loose.sum())

    def test_batch_equals_single(self):
        fb = FrameBuilder(Config())
        g = torch.cat([central_gradients(spherical_cap(cc=cc)).float() for cc in (-30.0, 0.0, 25.0)])
        batch = fb.from_gradients(g, index=torch.tensor([3, 4, 5]))
        for i in range(3):
            single = fb.from_gradients(g[i : i + 1])
            torch.testing.assert_close(batch[i].height, single.height)
            assert torch.equal(batch[i].contact, single.contact)
            torch.testing.assert_close(batch[i].curvature, single.curvature)
        assert batch.index.tolist() == [3, 4, 5]
        assert len(Frame.cat([batch[0], batch[2]])) == 2

    def test_float32_vs_float64_inputs(self):
        fb = FrameBuilder(Config())
        g64 = central_gradients(spherical_cap())
        f32 = fb.from_gradients(g64.float())
        f64 = fb.from_gradients(g64)
        torch.testing.assert_close(f32.height, f64.height)

    def test_device(self, device):
        fb = FrameBuilder(Config())
        f, _ = _ball_frame(fb)
        f2 = f.to(device)
        assert f2.height.device.type == device.type

    @pytest.mark.parametrize(
        "bad,match",
        [
            (torch.zeros(240, 320, 2), r"\(B, H, W, 2\)"),
            (torch.zeros(1, 100, 320, 2), "size"),
            (torch.full((1, 240, 320, 2), float("nan")), "NaN"),
            (torch.zeros(0, 240, 320, 2), "empty"),
        ],
    )
    def test_bad_gradients(self, bad, match):
        with pytest.raises(InputError, match=match):
            FrameBuilder(Config()).from_gradients(bad)

    def test_mask_shape_mismatch(self):
        with pytest.raises(InputError, match="contact masks"):
            FrameBuilder(Config()).from_gradients(torch.zeros(1, 240, 320, 2), contact=torch.zeros(1, 10, 10))

    def test_float_masks_must_be_zero_or_one(self):
        """A float mask of 0.4 or NaN is no mask; before, ``.bool()`` made both contact.
        Integer masks count nonzero as contact (0/255 images)."""
        fb = FrameBuilder(Config())
        g = central_gradients(spherical_cap()).float()
        m = torch.zeros(1, 240, 320)
        m[0, 100:140, 140:180] = 1.0
        assert torch.equal(fb.from_gradients(g, contact=m).contact, m.bool())
        assert torch.equal(fb.from_gradients(g, contact=(m * 255).to(torch.uint8)).contact, m.bool())
        for stray in (0.4, float("nan")):
            bad = m.clone()
            bad[0, 0, 0] = stray
            with pytest.raises(InputError, match="float contact masks must be 0 or 1, got values such as"):
                fb.from_gradients(g, contact=bad)

    def test_numpy_inputs_equal_tensors(self):
        """numpy gradients and masks (e.g. read with np.load) give the tensors' frame."""
        fb = FrameBuilder(Config())
        g = central_gradients(spherical_cap()).float()
        contact = fb.from_gradients(g).contact
        ref = fb.from_gradients(g, contact)
        arr = fb.from_gradients(g.numpy(), contact.numpy())
        assert torch.equal(arr.height, ref.height) and torch.equal(arr.contact, ref.contact)
        assert torch.equal(fb.from_gradients(g.numpy()).height, fb.from_gradients(g).height)

    @pytest.mark.parametrize("bad, match", [([[0.0]], "gradients must be a torch tensor or a numpy array, got list"),
                                            (np.zeros((240, 320, 2)), r"add a batch axis \(x\[None\]\)")])
    def test_bad_gradient_types(self, bad, match):
        with pytest.raises(InputError, match=match):
            FrameBuilder(Config()).from_gradients(bad)


@pytest.fixture(scope="module")
def real(mini_data):
    model, _ = load_model(mini_data / "reference_model" / "nnmodel.pth")
    bg = presses.load_background(mini_data)
    return mini_data, FrameBuilder(Config(), GradientDecoder(model, bg)), presses.catalog(mini_data)


class TestRealPresses:
    def test_contact_mask_overlaps_ball_disc(self, real):
        root, fb, cat = real
        ious = []
        for reldir, diam in cat[::3]:
            f = fb.from_bgr(presses.load_press(root, reldir)[None])
            cx, cy, rad = presses.fit_disc(f.gradients[0].numpy(), diam)
            yy, xx = np.mgrid[0:240, 0:320]
            disc = np.hypot(xx - cx, yy - cy) <= rad
            c = f.contact[0].numpy()
            ious.append((c & disc).sum() / max((c | disc).sum(), 1))
        assert np.median(ious) >= 0.7, ious

    def test_reference_model_matches_analytic_ball(self, real):
        root, fb, cat = real
        errs = []
        for reldir, diam in cat[::4]:
            f = fb.from_bgr(presses.load_press(root, reldir)[None])
            g = f.gradients[0].numpy()
            cx, cy, rad = presses.fit_disc(g, diam)
            big_r = diam / presses.MM_PER_PX / 2
            yy, xx = np.mgrid[0:240, 0:320]
            dx, dy = xx - cx, yy - cy
            inside = np.hypot(dx, dy) < rad - 4
            dz = np.sqrt(np.clip(big_r**2 - dx**2 - dy**2, 1e-9, None))
            true = np.stack([np.arctan2(dx, dz), np.arctan2(dy, dz)], -1)[inside]
            est = np.arctan(g[inside])
            errs.append(np.abs(est - true))
        mae = float(np.concatenate(errs).mean())
        assert 0.02 < mae < 0.15, mae

    def test_batch_equals_single_bgr(self, real):
        root, fb, cat = real
        imgs = torch.stack([presses.load_press(root, r) for r, _ in cat[:3]])
        batch = fb.from_bgr(imgs)
        single = fb.from_bgr(imgs[1:2])
        torch.testing.assert_close(batch[1].gradients, single.gradients)
        assert torch.equal(batch[1].contact, single.contact)
        assert batch.decoded and batch[1].decoded and single.decoded  # from images: the decoder's slopes

    def test_mlp_skip_barely_changes_geometry(self, real):
        """Skipping unchanged pixels must not move the contact or the depth."""
        root, fb, cat = real
        img = presses.load_press(root, cat[5][0])[None]
        cfg = Config()
        cfg.contact.mlp_skip_color_dist = 0.0
        full = FrameBuilder(cfg, fb.decoder).from_bgr(img)
        fast = fb.from_bgr(img)
        c1, c2 = full.contact[0], fast.contact[0]
        assert (c1 & c2).sum() / (c1 | c2).sum() > 0.95
        assert abs(float(full.height.min() - fast.height.min())) < 0.05 * abs(float(full.height.min()))

    @pytest.mark.parametrize(
        "bad,match",
        [
            (torch.zeros(1, 120, 160, 3, dtype=torch.uint8), "shape"),
            (torch.full((1, 240, 320, 3), float("nan")), "NaN"),
        ],
    )
    def test_bad_images(self, real, bad, match):
        with pytest.raises(InputError, match=match):
            real[1].from_bgr(bad)

    def test_numpy_images_equal_tensors(self, real):
        """OpenCV frames (numpy uint8, not contiguous after a channel flip) are taken as is."""
        root, fb, cat = real
        img = presses.load_press(root, cat[2][0])[None]
        flipped = np.ascontiguousarray(img.numpy()[..., ::-1])[..., ::-1]  # a non-contiguous view, same pixels
        assert not flipped.flags.c_contiguous
        torch.testing.assert_close(fb.from_bgr(flipped).gradients, fb.from_bgr(img).gradients, rtol=0, atol=0)
        with pytest.raises(InputError, match="add a batch axis"):
            fb.from_bgr(img[0].numpy())

    def test_from_bgr_needs_decoder(self):
        with pytest.raises(InputError, match="calibration model"):
            FrameBuilder(Config()).from_bgr(torch.zeros(1, 240, 320, 3, dtype=torch.uint8))


def test_ring_contact_keeps_unpressed_centre():
    """Hole filling of the colour mask must not put an unpressed centre in contact."""
    from tactile_slam.geometry.contact import contact_mask

    from .surfaces import grid

    r, c = grid()
    rad = torch.sqrt(r**2 + c**2)
    h = torch.where((rad > 20) & (rad < 45), torch.tensor(-10.0, dtype=torch.float64),
                    torch.tensor(0.0, dtype=torch.float64))[None]
    colour = torch.zeros(1, 240, 320, dtype=torch.bool)
    colour[0] = rad < 47  # a filled colour mask
    _, eroded = contact_mask(h, colour, 3.155, 85.0, 5)
    assert not eroded[0][rad < 15].any()
    assert eroded[0][(rad > 25) & (rad < 40)].all()


class TestDepthRule:
    """The contact depth test: the public fixed 0.2 mm threshold, or, for a touch not much
    deeper than it, the part deeper than half its depth (``contact.height_fraction``)."""

    @staticmethod
    def _press(depth_mm: float):
        from .surfaces import grid, spherical_cap

        r, c = grid()
        radius = 4.0 / 0.0634  # a 4 mm ball
        h = spherical_cap(radius=radius, depth=depth_mm / 0.0634)[None]
        colour = (h < 0) | (r**2 + c**2 < 3.0)[None]  # the colour change covers the cap
        return h, colour, radius

    @pytest.mark.parametrize("depth_mm", [0.12, 0.18])
    def test_shallow_touch_keeps_its_deeper_half(self, depth_mm):
        from tactile_slam.geometry.contact import contact_mask

        h, colour, radius = self._press(depth_mm)
        d = depth_mm / 0.0634
        fixed, _ = contact_mask(h, colour, 0.2 / 0.0634, 85.0, 5)
        assert not fixed.any()  # shallower than 0.2 mm: the public rule sees nothing
        raw, eroded = contact_mask(h, colour, 0.2 / 0.0634, 85.0, 5, fraction=0.5, floor_px=0.05 / 0.0634)
        # deeper than d/2 on a sphere: a disc of radius^2 = R^2 - (R - d/2)^2
        expected = math.pi * (radius**2 - (radius - d / 2) ** 2)
        assert abs(int(raw.sum()) - expected) < 0.05 * expected
        r_eroded = math.sqrt(expected / math.pi) - 2.5  # the final 5 x 5 erosion takes a ~2 px ring
        assert int(eroded.sum()) > 0.9 * math.pi * r_eroded**2

    def test_deep_press_keeps_the_fixed_threshold(self):
        from tactile_slam.geometry.contact import contact_mask

        h, colour, _ = self._press(0.8)
        a = contact_mask(h, colour, 0.2 / 0.0634, 85.0, 5)
        b = contact_mask(h, colour, 0.2 / 0.0634, 85.0, 5, fraction=0.5, floor_px=0.05 / 0.0634)
        assert torch.equal(a[0], b[0]) and torch.equal(a[1], b[1])

    def test_floor_and_height_only_input(self):
        from tactile_slam.geometry.contact import contact_mask

        h, colour, _ = self._press(0.04)  # shallower than the 0.05 mm floor
        assert not contact_mask(h, colour, 0.2 / 0.0634, 85.0, 5, fraction=0.5, floor_px=0.05 / 0.0634)[0].any()
        h, _, _ = self._press(0.15)  # without a colour mask the fixed rule applies
        assert not contact_mask(h, None, 0.2 / 0.0634, 85.0, 5, fraction=0.5, floor_px=0.05 / 0.0634)[0].any()

    def test_config(self):
        from tactile_slam.config import ConfigError

        cfg = Config()
        assert cfg.depth_test == pytest.approx((0.2 / 0.0634, 0.5, 0.05 / 0.0634))
        cfg.contact.height_fraction = None
        assert cfg.depth_test[1] is None
        for bad in (1.5, 0.0, float("nan")):
            cfg.contact.height_fraction = bad
            with pytest.raises(ConfigError, match="height_fraction"):
                FrameBuilder(cfg)
        cfg.contact.height_fraction = 0.5
        for bad in (-0.01, float("nan"), float("inf")):
            cfg.contact.min_depth_mm = bad
            with pytest.raises(ConfigError, match="min_depth_mm"):
                FrameBuilder(cfg)


def test_depth_unknown_when_the_object_covers_the_gel():
    """Pressed flat on a face larger than the sensor (the simulator's 30 mm slab), no
    undeformed gel is in view: 0.3, 0.8 and 1.2 mm deep give the same heights, and the
    frames say their depth is not known. A touch on the 9 mm seed leaves a rim of free
    gel: its depth is known and its heights reach the press depth."""
    from tactile_slam.sim.motions import pressed_poses
    from tactile_slam.sim.objects import make_object
    from tactile_slam.sim.renderer import GelRenderer

    cfg = Config()
    depths = np.array([0.3e-3, 0.8e-3, 1.2e-3])
    out = {}
    for name in ("plane", "seed"):
        renderer = GelRenderer(make_object(name), cfg)
        top = np.array([[0.0, 0.0, np.asarray(renderer.mesh.vertices)[:, 2].max()]])
        poses = pressed_poses(renderer, top.repeat(3, 0), np.array([[0.0, 0.0, 1.0]] * 3),
                              np.array([[1.0, 0.0, 0.0]] * 3), np.zeros(3), np.zeros(3), np.zeros(3), depths)
        maps = renderer.render(poses)
        out[name] = FrameBuilder(cfg).from_gradients(maps.gradients, maps.contact)
    plane, seed = out["plane"], out["seed"]
    assert plane.depth_known.tolist() == [False] * 3 and seed.depth_known.tolist() == [True] * 3
    # the same heights to float rounding (1.5e-6 mm), while the true depths differ by 0.9 mm
    torch.testing.assert_close(plane.height[1:], plane.height[:1].expand(2, -1, -1), rtol=0.0, atol=1e-4)
    deepest_mm = -seed.height.amin(dim=(1, 2)).double() * cfg.sensor.mm_per_px
    np.testing.assert_allclose(deepest_mm.numpy(), depths * 1e3, atol=0.05)


def test_clone_owns_its_maps():
    """``frames[i]`` shares the batch's storage; ``clone`` copies just that frame, equal
    in value, so a kept frame does not pin the batch."""
    z = torch.rand(3, 5, 6)
    batch = Frame(gradients=torch.rand(3, 5, 6, 2), height=z, contact=z > 0.5, normals=torch.rand(3, 5, 6, 3),
                  curvature=-z, in_contact=torch.ones(3, dtype=torch.bool), depth_known=torch.ones(3, dtype=torch.bool),
                  index=torch.arange(3), timestamp=torch.arange(3, dtype=torch.float64), mm_per_px=0.0634)
    view, copy = batch[1], batch[1].clone()
    for name in ("gradients", "height", "contact", "normals", "curvature", "depth_known", "index", "timestamp"):
        v, c = getattr(view, name), getattr(copy, name)
        assert torch.equal(v, c)
        assert v.untyped_storage().data_ptr() == getattr(batch, name).untyped_storage().data_ptr()
        assert c.untyped_storage().nbytes() == c.numel() * c.element_size()
    assert copy.mm_per_px == batch.mm_per_px


def test_frames_without_gradients():
    """A stored keyframe drops its gradients: size, batch, device, slicing, moving and
    concatenation still work, and a batch with such a frame has none either."""
    z = torch.rand(2, 5, 6)
    full = Frame(gradients=torch.rand(2, 5, 6, 2), height=z, contact=z > 0.5, normals=torch.rand(2, 5, 6, 3),
                 curvature=-z, in_contact=torch.ones(2, dtype=torch.bool), depth_known=torch.ones(2, dtype=torch.bool),
                 index=torch.arange(2), timestamp=torch.arange(2, dtype=torch.float64), mm_per_px=0.0634)
    bare = replace(full[1].clone(), gradients=None)
    assert bare.gradients is None and len(bare) == 1 and bare.shape == (5, 6) and bare.device == full.device
    assert torch.equal(bare.normals, full.normals[1:]) and bare.to("cpu")[0].gradients is None
    both = Frame.cat([full[0], bare])
    assert both.gradients is None and torch.equal(both.height, full.height)
    assert torch.equal(Frame.cat([full[0], full[1]]).gradients, full.gradients)


def _touch(dtype=torch.float32, device="cpu", rows=(20, 30), cols=(40, 52), shape=(60, 80), seed=0):
    """One frame with random maps everywhere and a rectangular contact."""
    g = torch.Generator().manual_seed(seed)
    h, w = shape
    contact = torch.zeros(1, h, w, dtype=torch.bool)
    contact[0, rows[0]:rows[1], cols[0]:cols[1]] = True
    return Frame(gradients=torch.randn(1, h, w, 2, generator=g, dtype=dtype),
                 height=torch.randn(1, h, w, generator=g, dtype=dtype), contact=contact,
                 normals=torch.randn(1, h, w, 3, generator=g, dtype=dtype),
                 curvature=torch.randn(1, h, w, generator=g, dtype=dtype), in_contact=torch.tensor([True]),
                 depth_known=torch.tensor([True]), index=torch.tensor([42]),
                 timestamp=torch.tensor([1.5], dtype=torch.float64),
                 mm_per_px=0.0634).to(device)


class TestCropToContact:
    """Keyframes store their maps around the contact (:class:`CroppedFrame`)."""

    @pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
    def test_box_and_expand(self, dtype, device):
        fr = _touch(dtype, device)
        crop = crop_to_contact(fr, margin=5)
        box = crop.box
        assert (crop.top, crop.left, tuple(box.height.shape)) == (15, 35, (1, 20, 22)) and box.gradients is None
        assert box.normals.shape == (1, 20, 22, 3) and box.contact.dtype == torch.bool
        assert len(crop) == 1 and crop.shape == (60, 80) and crop.device == fr.device and crop.mm_per_px == fr.mm_per_px
        assert box.height.dtype == dtype
        assert box.height.untyped_storage().nbytes() == 20 * 22 * box.height.element_size()
        full = crop.expand()
        assert full.gradients is None and full.shape == fr.shape and full.height.dtype == dtype
        box = (slice(None), slice(15, 35), slice(35, 57))
        for name in ("height", "normals", "curvature", "contact"):
            assert torch.equal(getattr(full, name)[box], getattr(fr, name)[box])
        assert torch.equal(full.contact, fr.contact)
        outside = torch.ones(1, 60, 80, dtype=torch.bool, device=device)
        outside[box] = False
        assert (full.height[outside] == 0).all() and (full.curvature[outside] == 0).all()
        flat = torch.tensor([0.0, 0.0, 1.0], dtype=dtype, device=device)
        assert torch.equal(full.normals[outside], flat.expand(int(outside.sum()), 3))
        assert (int(full.index[0]), float(full.timestamp[0]), bool(full.in_contact[0])) == (42, 1.5, True)

    def test_box_is_clipped_at_the_image_edge(self):
        crop = crop_to_contact(_touch(rows=(0, 4), cols=(75, 80)))
        assert (crop.top, crop.left, tuple(crop.box.height.shape)) == (0, 67, (1, 12, 13))
        assert torch.equal(crop.expand().contact, _touch(rows=(0, 4), cols=(75, 80)).contact)

    def test_no_contact_keeps_an_empty_box(self):
        fr = replace(_touch(), contact=torch.zeros(1, 60, 80, dtype=torch.bool))
        crop = crop_to_contact(fr)
        assert crop.box.height.numel() == 0
        full = crop.expand()
        assert not full.contact.any() and (full.height == 0).all() and (full.normals[..., 2] == 1).all()

    def test_owns_its_maps(self):
        batch = Frame.cat([_touch(seed=i) for i in range(3)])
        crop = crop_to_contact(batch[1])
        assert crop.box.height.untyped_storage().data_ptr() != batch.height.untyped_storage().data_ptr()
        batch.height.zero_()
        assert crop.box.height.abs().sum() > 0

    def test_full_batch_of_frames_and_crops(self, device):
        """Crops pasted into one batch equal their expansions; full frames are copied."""
        a, b, c = (_touch(device=device, seed=i) for i in range(3))
        crop_b = crop_to_contact(replace(b, depth_known=torch.tensor([False], device=device)))
        mixed = full_batch([a, crop_b, Frame.cat([c, a])])
        want = Frame.cat([replace(a, gradients=None), crop_b.expand(), replace(c, gradients=None),
                          replace(a, gradients=None)])
        assert len(mixed) == 4 and mixed.gradients is None and mixed.depth_known.tolist() == [True, False, True, True]
        for name in ("height", "contact", "normals", "curvature", "in_contact", "depth_known", "index", "timestamp"):
            assert torch.equal(getattr(mixed, name), getattr(want, name)), name
        assert torch.equal(full_batch([a, c]).gradients, Frame.cat([a, c]).gradients)  # all full: Frame.cat
        # decoded (from images) survives cropping and pasting, and marks a batch holding any such frame
        assert not mixed.decoded and not a.decoded
        crop_d = crop_to_contact(replace(b, decoded=True))
        assert crop_d.decoded and crop_d.expand().decoded
        assert full_batch([a, crop_d]).decoded and Frame.cat([replace(a, decoded=True), c]).decoded
        assert replace(a, decoded=True)[0].decoded and replace(a, decoded=True).clone().to(device).decoded
        with pytest.raises(InputError, match="empty"):
            full_batch([])
        with pytest.raises(InputError, match="different sizes"):
            full_batch([crop_b, _touch(shape=(40, 80), rows=(5, 9), device=device)])

    @pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
    def test_window_reads_as_the_expanded_frame(self, dtype, device):
        """A window's height and contact are those of the expanded crop, for windows
        inside, straddling and outside the box, and views of a full frame's maps."""
        fr = _touch(dtype, device)
        crop = crop_to_contact(fr, margin=3)
        full = crop.expand()
        for rows, cols in ((slice(20, 30), slice(40, 50)), (slice(0, 60), slice(0, 80)), (slice(10, 25), slice(30, 45)),
                           (slice(50, 60), slice(0, 10))):
            height, contact = height_and_contact_in(crop, rows, cols)
            assert height.dtype == dtype and contact.dtype == torch.bool and height.device == fr.device
            assert torch.equal(height, full.height[0, rows, cols]) and torch.equal(contact, full.contact[0, rows, cols])
            h_full, c_full = height_and_contact_in(fr, rows, cols)
            assert torch.equal(h_full, fr.height[0, rows, cols]) and torch.equal(c_full, fr.contact[0, rows, cols])
        with pytest.raises(InputError, match="B = 1"):
            height_and_contact_in(Frame.cat([fr, fr]), slice(0, 2), slice(0, 2))
        with pytest.raises(InputError, match="B = 1"):
            contact_bounds(Frame.cat([fr, fr]))
        for rows, cols in ((slice(50, 61), slice(0, 10)), (slice(5, 5), slice(0, 10)), (slice(0, 10), slice(-2, 3)),
                           (slice(None), slice(0, 10))):
            for part in (crop, fr):
                with pytest.raises(InputError, match="window"):
                    height_and_contact_in(part, rows, cols)
        rows, cols = fr.contact[0].nonzero(as_tuple=True)
        want = (int(rows.min()), int(rows.max()), int(cols.min()), int(cols.max()))
        assert contact_bounds(crop) == contact_bounds(fr) == want
        assert contact_bounds(replace(fr, contact=torch.zeros_like(fr.contact))) is None
        # a window around the bounds, clipped to the image
        assert window_around((5, 10, 70, 78), 3, (60, 80)) == (slice(2, 14), slice(67, 80))
        assert window_around((0, 59, 0, 79), 8, (60, 80)) == (slice(0, 60), slice(0, 80))

    def test_exceptions(self):
        two = Frame.cat([_touch(), _touch()])
        with pytest.raises(InputError, match="one frame"):
            crop_to_contact(two)
        with pytest.raises(InputError, match="margin"):
            crop_to_contact(_touch(), margin=2)


def _batch_of_three():
    z = torch.rand(3, 5, 6)
    return Frame(gradients=torch.rand(3, 5, 6, 2), height=z, contact=z > 0.5, normals=torch.rand(3, 5, 6, 3),
                 curvature=-z, in_contact=torch.ones(3, dtype=torch.bool), depth_known=torch.ones(3, dtype=torch.bool),
                 index=torch.arange(3), timestamp=torch.arange(3, dtype=torch.float64), mm_per_px=0.0634)


def test_integer_indexing_and_iteration():
    """``frames[i]`` keeps the batch axis, counts from the end when negative and raises
    IndexError outside the batch, so ``for frame in frames`` visits each frame once and
    stops (a slice past the end would have been an empty batch, forever)."""
    batch = _batch_of_three()
    for i, j in ((0, 0), (2, 2), (-1, 2), (-2, 1), (-3, 0)):
        assert len(batch[i]) == 1 and int(batch[i].index) == j
    for i in (3, -4, 100):
        with pytest.raises(IndexError, match=f"index {i} is out of range for a batch of 3"):
            batch[i]
    assert [int(f.index) for f in batch] == [0, 1, 2]
    assert [len(f) for f in batch] == [1, 1, 1]
    crops = [crop_to_contact(_touch(seed=i)) for i in range(2)]
    wb = window_batch(crops, 4)
    assert [torch.equal(w.maps.height, wb.maps.height[i:i + 1]) for i, w in enumerate(wb)] == [True, True]
    with pytest.raises(IndexError):
        wb[2]


class TestWindowBatch:
    """Targets of a batched registration in windows of one size around their boxes."""

    @pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
    def test_windows_hold_the_grown_boxes_and_expand_to_the_full_batch(self, dtype, device):
        crops = [crop_to_contact(_touch(dtype, device, rows=r, cols=c, seed=i), margin=3)
                 for i, (r, c) in enumerate((((20, 30), (40, 52)), ((2, 9), (60, 78)), ((45, 58), (5, 15))))]
        for m in (1, 4, 20):
            wb = window_batch(crops, m)
            h, w = wb.maps.shape
            assert len(wb) == 3 and wb.shape == (60, 80) and wb.device == crops[0].device and wb.maps.gradients is None
            assert wb.origins.dtype == torch.int64 and wb.origins.shape == (3, 2) and wb.mm_per_px == 0.0634
            assert h % m == 0 and w % m == 0 and not (wb.origins % m).any()
            for (top, left), crop in zip(wb.origins.tolist(), crops):
                bh, bw = crop.box.shape
                # the box grown by m on every side (as far as the image goes) is inside the window
                assert top <= max(crop.top - m, 0) and top + h >= min(crop.top + bh + m, 60)
                assert left <= max(crop.left - m, 0) and left + w >= min(crop.left + bw + m, 80)
            want = full_batch(crops)
            got = wb.expand()
            for name in ("height", "contact", "normals", "curvature", "in_contact", "depth_known", "index",
                         "timestamp"):
                assert torch.equal(getattr(got, name), getattr(want, name)), (m, name)
        wb = window_batch(crops, 4)
        assert torch.equal(wb[2].origins, wb.origins[2:]) and torch.equal(wb[2].maps.height, wb.maps.height[2:])
        pick = wb[torch.tensor([2, 0], device=device)]
        assert torch.equal(pick.origins, wb.origins[[2, 0]]) and torch.equal(pick.expand().height,
                                                                             full_batch([crops[2], crops[0]]).height)

    def test_a_full_frame_makes_every_window_the_image(self, device):
        fr, crop = _touch(device=device), crop_to_contact(_touch(device=device, seed=1, rows=(2, 9)))
        wb = window_batch([crop, fr], 4)
        assert wb.maps.shape == (60, 80) and not wb.origins.any()
        assert torch.equal(wb.maps.normals, full_batch([crop, fr]).normals)

    def test_crops_without_contact_get_two_pixel_windows(self):
        empty = crop_to_contact(replace(_touch(), contact=torch.zeros(1, 60, 80, dtype=torch.bool)))
        wb = window_batch([empty, empty], 1)
        assert wb.maps.shape == (2, 2) and not wb.maps.contact.any() and (wb.maps.normals[..., 2] == 1).all()
        assert torch.equal(wb.expand().height, full_batch([empty, empty]).height)

    def test_exceptions(self):
        crop = crop_to_contact(_touch())
        with pytest.raises(InputError, match="empty"):
            window_batch([])
        with pytest.raises(InputError, match="alignment"):
            window_batch([crop], 7)  # does not divide 60 x 80
        with pytest.raises(InputError, match="alignment"):
            window_batch([crop], 0)
        with pytest.raises(InputError, match="different sizes"):
            window_batch([crop, _touch(shape=(40, 80), rows=(5, 9))])
