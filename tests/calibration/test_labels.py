import math

import cv2
import numpy as np
import pytest
import torch

from tactile_slam.calibration.catalog import CalibrationDataError, load_calibration_set
from tactile_slam.calibration.labels import (
    PIXEL_SCALE_MM,
    DetectionConfig,
    NoContactError,
    PressLabel,
    detect_contact_circle,
    indentation_px,
    label_presses,
    read_labels,
    rim_margin_px,
    write_labels,
    write_overlays,
)
from tactile_slam.calibration.model import pixel_features

from .conftest import MM_PER_PX, SYNTHETIC_PRESSES, press_image, render, synthetic_background

R_SMALL = 6.31 / MM_PER_PX / 2


def _detect(img, bg, ball_r=R_SMALL, max_ind=2.0 / MM_PER_PX, **kw):
    return detect_contact_circle(img, bg, ball_r, max_ind, DetectionConfig(**kw) if kw else DetectionConfig())


class TestDetectSynthetic:
    @pytest.mark.parametrize("cx, cy, a", [(160.0, 120.0, 25.0), (87.3, 150.6, 28.0), (250.2, 60.4, 18.0)])
    def test_interior_press(self, cx, cy, a):
        bg = synthetic_background()
        lb = _detect(press_image(cx, cy, a, 6.31), bg)
        assert lb.reliable, lb.reason
        assert abs(lb.cx - cx) < 0.5 and abs(lb.cy - cy) < 0.5
        assert abs(lb.radius - a) < 1.0
        assert lb.visible > 0.95

    def test_large_ball(self):
        bg = synthetic_background()
        lb = _detect(press_image(140.0, 110.0, 36.0, 9.5), bg, ball_r=9.5 / MM_PER_PX / 2)
        assert lb.reliable and abs(lb.radius - 36.0) < 1.0

    def test_border_press_keeps_centre(self):
        # centre 12 px from the left edge: the region's centroid is biased inward, the rim fit is not
        bg = synthetic_background()
        lb = _detect(press_image(12.0, 120.0, 26.0, 6.31), bg)
        assert abs(lb.cx - 12.0) < 1.0 and abs(lb.cy - 120.0) < 1.0 and abs(lb.radius - 26.0) < 1.0
        assert 0.5 < lb.visible < 0.9

    def test_mostly_outside_is_flagged(self):
        bg = synthetic_background()
        lb = _detect(press_image(-12.0, 120.0, 26.0, 6.31), bg)
        assert not lb.reliable and "inside the image" in lb.reason

    @pytest.mark.parametrize("cx, cy, a", [(-5.0, 120.0, 26.0), (300.0, 20.0, 25.0), (160.0, 8.0, 27.0)])
    def test_visible_is_the_rim_inside_the_image(self, cx, cy, a):
        """``visible`` is the fraction of the fitted circle inside the image, not of the rays
        that found a peak: these presses have 44-59 % of their rim inside, the rays said
        64-67 % (before 2026-12-03), and two of them passed the 60 % check."""
        t = np.linspace(0.0, 2 * np.pi, 3600, endpoint=False)
        x, y = cx + a * np.cos(t), cy + a * np.sin(t)
        truth = float(((x >= 0) & (x <= 319) & (y >= 0) & (y <= 239)).mean())
        lb = _detect(press_image(cx, cy, a, 6.31), synthetic_background())
        assert abs(lb.visible - truth) < 0.03, (lb.visible, truth)
        assert not lb.reliable and f"only {lb.visible:.0%} of the rim is inside the image" in lb.reason

    def test_too_shallow_is_flagged(self):
        """A 25 px contact of a 6.31 mm ball catalogued as 63.1 mm (a typo): with that ball it
        would be 0.59 px deep (the 24.2 px rim found), less than the 1 px of the shallowest
        press the detector accepts."""
        lb = _detect(press_image(160.0, 120.0, 25.0, 6.31), synthetic_background(), ball_r=63.1 / MM_PER_PX / 2)
        assert not lb.reliable and "indentation 0.59 px < 1 px" in lb.reason and "catalog.csv" in lb.reason
        assert _detect(press_image(160.0, 120.0, 25.0, 6.31), synthetic_background(), ball_r=9.5 / MM_PER_PX / 2
                       ).reliable  # 4.3 px deep with the 9.5 mm ball: implausible only by its colours

    def test_too_deep_is_flagged(self):
        bg = synthetic_background()
        # a 30 px contact on a 49.76 px ball implies a 10.1 px indentation
        lb = _detect(press_image(160.0, 120.0, 30.0, 6.31), bg, max_ind=8.0)
        assert not lb.reliable and "indentation" in lb.reason
        assert indentation_px(lb.radius, R_SMALL) == pytest.approx(10.1, abs=0.7)

    def test_no_contact(self):
        bg = synthetic_background()
        img = render(bg, np.zeros((240, 320, 2)), seed=3)
        with pytest.raises(NoContactError, match="no visible contact"):
            detect_contact_circle(img, bg, R_SMALL, 31.5, reldir="6.310mm/7")

    def test_identical_images(self):
        bg = synthetic_background()
        with pytest.raises(NoContactError):
            detect_contact_circle(bg.copy(), bg, R_SMALL, 31.5)

    def test_bad_inputs(self):
        bg = synthetic_background()
        with pytest.raises(ValueError, match="must both be"):
            detect_contact_circle(bg[:100], bg, R_SMALL, 31.5)
        bad = bg.copy()
        bad[5, 5, 0] = np.nan
        with pytest.raises(ValueError, match="non-finite"):
            detect_contact_circle(bad, bg, R_SMALL, 31.5)

    def test_settled_detects_alternation(self):
        from tactile_slam.calibration.labels import _RimFit, _settled

        a, b = _RimFit(10.0, 10.0, 20.0, 1.0, 0.1, False), _RimFit(14.0, 12.0, 16.0, 1.0, 3.0, False)
        near = _RimFit(10.2, 10.0, 20.1, 1.0, 0.1, False)
        assert not _settled([a], 0.5) and not _settled([a, b], 0.5)
        assert _settled([a, near], 0.5)
        assert _settled([a, b, near], 0.5)  # a period-2 cycle
        assert not _settled([a, b, b._replace(cx=15.0)], 0.5)

    def test_unsettled_fit_is_flagged(self):
        bg = synthetic_background()
        lb = _detect(press_image(160.0, 120.0, 25.0, 6.31), bg, iterations=1, starts=1)
        assert not lb.reliable and "did not settle" in lb.reason

    def test_single_start(self):
        bg = synthetic_background()
        lb = _detect(press_image(160.0, 120.0, 25.0, 6.31), bg, starts=1)
        assert lb.reliable and abs(lb.radius - 25.0) < 1.0  # the centroid start alone still works

    @pytest.mark.parametrize("field, value", [("iterations", 0), ("starts", 0), ("settle_px", 0.0),
                                              ("settle_px", float("nan")), ("n_rays", 4)])
    def test_bad_config(self, field, value):
        with pytest.raises(ValueError, match=field):
            DetectionConfig(**{field: value})

    def test_indentation(self):
        assert indentation_px(0.0, 50.0) == 0.0
        assert indentation_px(30.0, 50.0) == pytest.approx(10.0)
        assert indentation_px(50.0, 50.0) == math.inf


class TestRealPresses:
    def test_geometry(self, mini_calib, mini_labels):
        reliable = [lb for lb in mini_labels.values() if lb.reliable]
        assert len(reliable) >= 0.9 * len(mini_calib.presses)
        for lb in reliable:
            ball_r = mini_calib.press(lb.reldir).ball_radius_px(MM_PER_PX)
            assert lb.radius < ball_r
            assert indentation_px(lb.radius, ball_r) <= 2.0 / MM_PER_PX
            # contact must not be tiny either: a 1 px deep press has a = sqrt(2 R)
            assert lb.radius > math.sqrt(2 * ball_r)

    def test_reference_model_agrees_with_labels(self, mini_calib, mini_labels, reference_model):
        """The SDK model (trained independently, on hand labels) predicts the analytic
        ball's angles inside our discs: method.md's yardstick is 0.099 rad with area labels."""
        from tactile_slam.calibration.dataset import sphere_targets

        errs, n = 0.0, 0
        for lb in mini_labels.values():
            if not lb.reliable:
                continue
            press = mini_calib.press(lb.reldir)
            ang, mask = sphere_targets((240, 320), lb.cx, lb.cy, lb.radius, press.ball_radius_px(MM_PER_PX))
            with torch.no_grad():
                pred = reference_model(pixel_features(torch.from_numpy(mini_calib.image(press))[None])[0][mask])
            errs += float((pred - ang[mask]).abs().sum()) / 2
            n += int(mask.sum())
        assert errs / n < 0.06

    def test_centres_match_independent_estimate(self, mini_calib, mini_labels, reference_model):
        """The centre that best fits the reference model's angles to the analytic ball (grid
        search over +-5 px, sphere angles computed here in numpy) lies within 3 px of the
        rim-fit centre for most presses."""
        reliable = [lb for lb in mini_labels.values() if lb.reliable][::3]
        close = 0
        for lb in reliable:
            press = mini_calib.press(lb.reldir)
            ball_r = press.ball_radius_px(MM_PER_PX)
            ys, xs = np.nonzero((np.arange(320)[None] - lb.cx) ** 2 + (np.arange(240)[:, None] - lb.cy) ** 2
                                < (lb.radius - 4) ** 2)
            with torch.no_grad():
                feats = pixel_features(torch.from_numpy(mini_calib.image(press))[None])[0][ys, xs]
                pred = reference_model(feats).numpy()
            best = (math.inf, 0, 0)
            for dx in range(-5, 6):
                for dy in range(-5, 6):
                    ex, ey = xs - (lb.cx + dx), ys - (lb.cy + dy)
                    ez = np.sqrt(np.maximum(ball_r**2 - ex**2 - ey**2, 1e-9))
                    err = (np.abs(pred[:, 0] - np.arctan2(ex, ez)).mean()
                           + np.abs(pred[:, 1] - np.arctan2(ey, ez)).mean())
                    best = min(best, (float(err), dx, dy))
            close += max(abs(best[1]), abs(best[2])) <= 3
        assert close >= 0.8 * len(reliable)

    # presses whose label the colour-distance peak of a single start got wrong by 9-23 px
    # under other LED gains (the old detector); the rim is the same whatever the colours
    @pytest.mark.parametrize("reldir", ["6.310mm/0", "6.310mm/22", "6.310mm/33", "6.310mm/38"])
    @pytest.mark.parametrize("gains, mirror", [((1.15, 0.9, 1.05), False), ((1.15, 0.9, 1.05), True),
                                               ((0.85, 1.1, 1.0), False)])
    def test_label_does_not_depend_on_led_colours(self, mini_calib, mini_labels, reldir, gains, mirror):
        press = mini_calib.press(reldir)
        ball_r = press.ball_radius_px(MM_PER_PX)

        def relit(img):
            out = img.astype(np.float32) * np.array(gains, dtype=np.float32) - 5.0
            return out[:, ::-1] if mirror else out

        lb = detect_contact_circle(relit(mini_calib.image(press)), relit(mini_calib.background), ball_r,
                                   2.0 / MM_PER_PX)
        ref = mini_labels[reldir]
        cx = 319.0 - lb.cx if mirror else lb.cx
        assert lb.reliable and ref.reliable, (lb.reason, ref.reason)
        assert abs(cx - ref.cx) < 1.5 and abs(lb.cy - ref.cy) < 1.5 and abs(lb.radius - ref.radius) < 1.5

    def test_corner_press_takes_the_outer_rim(self, mini_calib, mini_labels, reference_model):
        """Press 38 sits in a corner; rays from the region's centroid lock onto a colour
        ring inside the contact (radius 17 px, flagged). The rim encloses it: radius 29 px,
        where the SDK model (trained on hand labels) matches the analytic ball as well as
        on the other presses."""
        from tactile_slam.calibration.evaluate import evaluate_model

        lb = mini_labels["6.310mm/38"]
        assert lb.reliable and 27.0 < lb.radius < 31.0
        with torch.no_grad():
            ev = evaluate_model(reference_model, mini_calib, mini_labels, [lb.reldir], MM_PER_PX)
        assert ev.angle_mae < 0.05


    # (rows, columns) kept: the crops of the QA pass of 2026-12-03
    CROPS = {"left 40 cut": (slice(None), slice(40, None)), "top 25, right 30 cut": (slice(25, None), slice(None, 290)),
             "bottom 25, left 30 cut": (slice(None, 215), slice(30, None))}

    @pytest.mark.parametrize("crop", list(CROPS))
    def test_presses_cut_by_the_border(self, mini_calib, mini_labels, crop):
        """The presses and background cropped: a reliable label keeps the uncut label's circle
        (shifted into the crop) or is flagged. Rays that leave the image short of the rim used
        to add rim points inside the contact: 9.500mm/18 (bottom cut) came out 14 px off and
        6.310mm/33 (left cut) 18 px off, both reliable; now the worst reliable label is 7.3 px
        off (docs/calibration.md, "Presses cut by the border")."""
        rows, cols = self.CROPS[crop]
        bg = np.ascontiguousarray(mini_calib.background[rows, cols])
        dy, dx = rows.start or 0, cols.start or 0
        worst = 0.0
        for reldir, ref in mini_labels.items():
            press = mini_calib.press(reldir)
            lb = detect_contact_circle(np.ascontiguousarray(mini_calib.image(press)[rows, cols]), bg,
                                       press.ball_radius_px(MM_PER_PX), 2.0 / MM_PER_PX)
            off = max(math.hypot(lb.cx + dx - ref.cx, lb.cy + dy - ref.cy), abs(lb.radius - ref.radius))
            if reldir in ("6.310mm/33", "9.500mm/18", "6.310mm/38"):  # 25-44 % of the rim left: flagged
                assert not lb.reliable or off < 3.0, (reldir, off, lb)
            if lb.reliable:
                worst = max(worst, off)
        assert worst < 8.0


class TestScale:
    """Pixel settings are given at the Mini's 0.0634 mm/px and converted for other scales,
    so a press set recorded at another resolution gets the same physical tolerances."""

    def test_at_scale_converts_lengths_only(self):
        cfg = DetectionConfig()
        assert cfg.at_scale(PIXEL_SCALE_MM) == cfg
        half = cfg.at_scale(PIXEL_SCALE_MM / 2)  # twice the pixels per mm
        for name in ("blur_sigma", "settle_px", "max_residual_px", "min_radius_px"):
            assert getattr(half, name) == pytest.approx(2 * getattr(cfg, name))
        for name in ("noise_sigmas", "n_rays", "iterations", "starts", "min_visible"):
            assert getattr(half, name) == getattr(cfg, name)
        assert rim_margin_px(PIXEL_SCALE_MM) == 4.0 and rim_margin_px(PIXEL_SCALE_MM * 2) == pytest.approx(2.0)

    @pytest.mark.parametrize("mm_per_px", [0.0, -0.05, float("nan"), float("inf")])
    def test_bad_scale(self, mm_per_px):
        with pytest.raises(ValueError, match="mm_per_px"):
            DetectionConfig().at_scale(mm_per_px)

    @pytest.mark.parametrize("factor", [2.0, 0.5])
    def test_real_presses_resampled(self, mini_calib, mini_labels, factor):
        """The real presses resized to 640x480 (or 160x120) at the matching scale: every
        press labelled reliable at 320x240 is reliable there too, at the same circle (in
        320x240 pixels: centre and radius within 1.5 px, or one pixel of the smaller image,
        median within 0.6 px). With the
        Mini's pixel settings unconverted, seven of the 640x480 rims fail the residual test
        and one of the 160x120 rims the visibility test (``benchmarks/labels.json``)."""
        from tactile_slam.bench.labels import resampled

        scale = MM_PER_PX / factor
        res = resampled(mini_calib, mini_labels, factor, MM_PER_PX, 2.0, DetectionConfig().at_scale(scale))
        n_reliable = sum(lb.reliable for lb in mini_labels.values())
        assert not res["flagged"] and res["reliable"] == n_reliable, res["flagged"]
        centre, radius = res["centre_offset_px"], res["radius_difference_abs_px"]
        bound = max(1.5, 1.0 / factor)
        assert centre["max"] < bound and radius["max"] < bound, (centre, radius)
        assert centre["median"] < 0.6 and radius["median"] < 0.6


class TestLabelFiles:
    def test_roundtrip(self, tmp_path):
        labels = [PressLabel("6.310mm/0", 10.123, 20.456, 25.5), PressLabel("9.500mm/1", 1, 2, 30, False, "rim x")]
        path = write_labels(tmp_path / "labels.csv", labels)
        back = read_labels(path)
        assert list(back) == ["6.310mm/0", "9.500mm/1"]
        assert back["6.310mm/0"].cx == pytest.approx(10.12) and back["6.310mm/0"].reliable
        assert not back["9.500mm/1"].reliable and back["9.500mm/1"].reason == "rim x"
        assert all(lb.source == "file" for lb in back.values())

    def test_minimal_hand_written_file(self, tmp_path):
        (tmp_path / "l.csv").write_text("experiment_reldir,cx,cy,radius\n6.310mm/0,100,80,25\n")
        lb = read_labels(tmp_path / "l.csv")["6.310mm/0"]
        assert (lb.cx, lb.cy, lb.radius, lb.reliable) == (100.0, 80.0, 25.0, True)

    @pytest.mark.parametrize(
        "text, match",
        [
            ("reldir,x,y,r\n", "header"),
            ("experiment_reldir,cx,cy,radius\n6.310mm/0,a,80,25\n", "numbers"),
            ("experiment_reldir,cx,cy,radius\n6.310mm/0,1,80,-2\n", "radius > 0"),
            ("experiment_reldir,cx,cy,radius\n6.310mm/0,nan,80,2\n", "finite"),
            ("experiment_reldir,cx,cy,radius,reliable\n6.310mm/0,,,,1\n", "finite"),  # only flagged rows may
        ],
    )
    def test_bad_files(self, tmp_path, text, match):
        (tmp_path / "l.csv").write_text(text)
        with pytest.raises(CalibrationDataError, match=match):
            read_labels(tmp_path / "l.csv")

    def test_missing_file(self, tmp_path):
        with pytest.raises(CalibrationDataError, match="not found"):
            read_labels(tmp_path / "none.csv")


class TestLabelPresses:
    def test_detects_and_overrides(self, synthetic_calib):
        calib = load_calibration_set(synthetic_calib)
        override = {"6.310mm/1": PressLabel("6.310mm/1", 1.0, 2.0, 3.0, source="file")}
        labels = label_presses(calib, MM_PER_PX, 2.0, override)
        assert [lb.reldir for lb in labels] == [p.reldir for p in calib.presses]
        assert labels[1] == override["6.310mm/1"]
        for lb, (_, _, cx, cy, a) in zip(labels, SYNTHETIC_PRESSES):
            if lb.source == "auto":
                assert lb.reliable and abs(lb.cx - cx) < 0.7 and abs(lb.cy - cy) < 0.7 and abs(lb.radius - a) < 1.0

    def test_unknown_override(self, synthetic_calib):
        calib = load_calibration_set(synthetic_calib)
        with pytest.raises(CalibrationDataError, match="not in the catalog"):
            label_presses(calib, MM_PER_PX, 2.0, {"1.000mm/0": PressLabel("1.000mm/0", 1, 2, 3)})

    def test_press_without_contact(self, synthetic_calib, tmp_path):
        """One press without contact is flagged, not an error that stops the whole set
        (it raised NoContactError before 2026-12-03); its label file row has no circle."""
        cv2.imwrite(str(synthetic_calib / "9.500mm/0/gelsight.png"),
                    render(synthetic_background(), np.zeros((240, 320, 2)), seed=9))
        calib = load_calibration_set(synthetic_calib)
        labels = label_presses(calib, MM_PER_PX, 2.0)
        lb = labels[4]
        assert not lb.reliable and lb.reason.startswith("no contact") and math.isnan(lb.radius)
        assert all(other.reliable for other in labels[:4] + labels[5:])
        back = read_labels(write_labels(tmp_path / "labels.csv", labels))["9.500mm/0"]
        assert not back.reliable and math.isnan(back.radius) and back.reason == lb.reason
        write_overlays(calib, labels, tmp_path / "ov")  # draws no circle for it
        # a label from a file makes the press usable again
        given = PressLabel("9.500mm/0", 240, 70, 33, source="file")
        assert label_presses(calib, MM_PER_PX, 2.0, {"9.500mm/0": given})[4] is given

    def test_no_press_with_contact(self, synthetic_calib):
        for i, (reldir, *_) in enumerate(SYNTHETIC_PRESSES):
            cv2.imwrite(str(synthetic_calib / reldir / "gelsight.png"),
                        render(synthetic_background(), np.zeros((240, 320, 2)), seed=i))
        with pytest.raises(NoContactError, match="no press in .* shows contact, first: no contact.*6.310mm/0"):
            label_presses(load_calibration_set(synthetic_calib), MM_PER_PX, 2.0)

    def test_overlays(self, synthetic_calib, tmp_path):
        calib = load_calibration_set(synthetic_calib)
        labels = label_presses(calib, MM_PER_PX, 2.0)
        labels[0] = PressLabel(labels[0].reldir, labels[0].cx, labels[0].cy, labels[0].radius, False, "test")
        overview = write_overlays(calib, labels, tmp_path / "ov", columns=4)
        grid = cv2.imread(str(overview))
        assert grid.shape == (2 * 120, 4 * 160, 3)
        one = cv2.imread(str(tmp_path / "ov" / "6.310mm_0.png"))
        assert one.shape == (240, 320, 3)
        # the flagged circle is drawn in red on its rim
        lb = labels[0]
        rim = one[int(round(lb.cy)), int(round(lb.cx + lb.radius)) - 1: int(round(lb.cx + lb.radius)) + 2]
        assert (rim[:, 2] > 200).any()
