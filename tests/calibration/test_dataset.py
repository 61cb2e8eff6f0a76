import math

import pytest
import torch

from tactile_slam.calibration.catalog import CalibrationDataError, load_calibration_set
from tactile_slam.calibration.dataset import (build_dataset, press_samples, split_by_diameter, split_presses,
                                              sphere_targets)
from tactile_slam.calibration.labels import PressLabel, label_presses

from .conftest import MM_PER_PX, SYNTHETIC_PRESSES, write_calibration_folder


class TestSphereTargets:
    def test_shapes(self):
        ang, mask = sphere_targets((240, 320), 100.0, 80.0, 25.0, 49.76)
        assert ang.shape == (240, 320, 2) and ang.dtype == torch.float32
        assert mask.shape == (240, 320) and mask.dtype == torch.bool

    def test_values(self):
        cx, cy, ball_r = 100.0, 80.0, 49.76
        ang, mask = sphere_targets((240, 320), cx, cy, 25.0, ball_r)
        assert ang[80, 100].abs().max() == 0
        for dx, dy in [(10, 0), (0, -15), (7, 9)]:
            dz = math.sqrt(ball_r**2 - dx**2 - dy**2)
            got = ang[int(cy + dy), int(cx + dx)]
            assert got[0].item() == pytest.approx(math.atan2(dx, dz), abs=1e-6)
            assert got[1].item() == pytest.approx(math.atan2(dy, dz), abs=1e-6)
        # sign convention: the centre is lowest, gx > 0 right of it, gy > 0 below it
        assert ang[80, 110, 0] > 0 and ang[90, 100, 1] > 0 and ang[70, 100, 1] < 0
        assert (ang[~mask] == 0).all()

    def test_mask_area(self):
        _, mask = sphere_targets((240, 320), 160.3, 120.6, 30.0, 74.92, margin_px=4.0)
        assert int(mask.sum()) == pytest.approx(math.pi * 26.0**2, rel=0.02)
        _, mask = sphere_targets((240, 320), 160.3, 120.6, 30.0, 74.92, margin_px=0.0)
        assert int(mask.sum()) == pytest.approx(math.pi * 30.0**2, rel=0.02)

    def test_border_disc_is_clipped(self):
        _, mask = sphere_targets((240, 320), 0.0, 0.0, 24.0, 49.76)
        assert 0 < int(mask.sum()) < math.pi * 20.0**2 / 3

    def test_too_deep(self):
        with pytest.raises(ValueError, match="too deep"):
            sphere_targets((240, 320), 100.0, 80.0, 60.0, 49.76)

    def test_empty_disc(self):
        with pytest.raises(ValueError, match="no pixels"):
            sphere_targets((240, 320), 100.0, 80.0, 3.0, 49.76)


class TestSplit:
    def test_seeded_disjoint(self):
        names = [f"p{i}" for i in range(10)]
        a = split_presses(names, seed=3)
        assert a == split_presses(names, seed=3)
        assert len(a["train"]) == 8 and len(a["test"]) == 2
        assert sorted(a["train"] + a["test"]) == sorted(names)
        assert any(split_presses(names, seed=s) != a for s in range(4, 8))

    def test_bad(self):
        with pytest.raises(ValueError, match="no presses"):
            split_presses([], 0)
        with pytest.raises(ValueError, match="test_fraction"):
            split_presses(["a"], 0, test_fraction=1.0)


class TestSplitByDiameter:
    def test_holds_out_one_ball_size(self, synthetic_calib):
        calib = load_calibration_set(synthetic_calib)
        split = split_by_diameter(calib, 9.5)
        assert split == {"train": ["6.310mm/0", "6.310mm/1", "6.310mm/2", "6.310mm/3"],
                         "test": ["9.500mm/0", "9.500mm/1"]}
        assert split_by_diameter(calib, 6.31)["test"] == split["train"]

    def test_bad(self, synthetic_calib, tmp_path):
        calib = load_calibration_set(synthetic_calib)
        with pytest.raises(ValueError, match=r"no press of 4.0 mm .*\[6.31, 9.5\]"):
            split_by_diameter(calib, 4.0)
        one_size = load_calibration_set(write_calibration_folder(tmp_path / "one", SYNTHETIC_PRESSES[:4]))
        with pytest.raises(ValueError, match="every press .* is 6.31 mm: nothing to train on"):
            split_by_diameter(one_size, 6.31)

    def test_build_dataset_takes_the_split(self, synthetic_calib):
        """The given split decides which presses' pixels land in each part."""
        calib = load_calibration_set(synthetic_calib)
        labels = {lb.reldir: lb for lb in label_presses(calib, MM_PER_PX, 2.0)}
        data = build_dataset(calib, labels, MM_PER_PX, split=split_by_diameter(calib, 9.5))
        assert data.split["test"] == ["9.500mm/0", "9.500mm/1"]
        assert data.test.reldirs == ["9.500mm/0", "9.500mm/1"]
        assert data.train.reldirs == ["6.310mm/0", "6.310mm/1", "6.310mm/2", "6.310mm/3"]
        # the contact pixels of each part are those of its presses alone
        alone, _ = press_samples(calib, labels, ["9.500mm/0", "9.500mm/1"], MM_PER_PX)
        assert int((data.test.press >= 0).sum()) == len(alone)


class TestBuildDataset:
    def test_counts_and_background(self, synthetic_calib):
        calib = load_calibration_set(synthetic_calib)
        labels = {lb.reldir: lb for lb in label_presses(calib, MM_PER_PX, 2.0)}
        data = build_dataset(calib, labels, MM_PER_PX, seed=1, test_fraction=0.34)
        assert len(data.split["train"]) == 3 and len(data.split["test"]) == 3
        for part in (data.train, data.test):
            n_contact = int((part.press >= 0).sum())
            n_bg = int((part.press < 0).sum())
            assert n_bg == int(n_contact * 0.2)
            assert part.features.shape == (len(part), 5) and part.angles.shape == (len(part), 2)
            assert (part.angles[part.press < 0] == 0).all()
            assert ((part.features >= 0) & (part.features <= 1)).all()
        # background samples of train and test do not overlap
        bg_tr = {tuple(f.tolist()) for f in data.train.features[data.train.press < 0][:, 3:]}
        bg_te = {tuple(f.tolist()) for f in data.test.features[data.test.press < 0][:, 3:]}
        assert not bg_tr & bg_te
        again = build_dataset(calib, labels, MM_PER_PX, seed=1, test_fraction=0.34)
        assert torch.equal(again.train.features, data.train.features)

    def test_skips_unreliable_and_too_deep(self, synthetic_calib):
        calib = load_calibration_set(synthetic_calib)
        labels = {lb.reldir: lb for lb in label_presses(calib, MM_PER_PX, 2.0)}
        labels["6.310mm/0"] = PressLabel("6.310mm/0", 100, 80, 25, reliable=False, reason="hand-flagged")
        labels["6.310mm/1"] = PressLabel("6.310mm/1", 220, 150, 70)  # 70 - 4 > 49.76: too deep
        samples, skipped = press_samples(calib, labels, ["6.310mm/0", "6.310mm/1", "6.310mm/2"], MM_PER_PX)
        assert samples.reldirs == ["6.310mm/2"]
        assert "hand-flagged" in skipped["6.310mm/0"] and "too deep" in skipped["6.310mm/1"]

    @pytest.mark.parametrize("factor", [1.0, 2.0])
    def test_rim_margin_follows_the_scale(self, synthetic_calib, factor):
        """The default margin is 4 px at 0.0634 mm/px, i.e. 0.2536 mm: twice the pixels at
        half the mm per pixel (the same labelled disc then keeps radius - 8 px)."""
        calib = load_calibration_set(synthetic_calib)
        label = PressLabel("6.310mm/2", 160.2, 120.7, 30.0)
        samples, skipped = press_samples(calib, {"6.310mm/2": label}, ["6.310mm/2"], MM_PER_PX / factor)
        assert not skipped
        assert len(samples) == pytest.approx(math.pi * (30.0 - 4.0 * factor) ** 2, rel=0.02)

    def test_missing_label(self, synthetic_calib):
        calib = load_calibration_set(synthetic_calib)
        with pytest.raises(CalibrationDataError, match="has no label"):
            press_samples(calib, {}, ["6.310mm/0"], MM_PER_PX)

    def test_nothing_to_train(self, synthetic_calib):
        calib = load_calibration_set(synthetic_calib)
        labels = {p.reldir: PressLabel(p.reldir, 1, 1, 20, reliable=False) for p in calib.presses}
        with pytest.raises(CalibrationDataError, match="no usable training press"):
            build_dataset(calib, labels, MM_PER_PX)
