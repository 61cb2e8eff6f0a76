import shutil
import warnings

import cv2
import numpy as np
import pytest

from tactile_slam.calibration.catalog import CalibrationDataError, CatalogWarning, load_calibration_set, read_catalog


class TestLoadCalibrationSet:
    def test_smoke_synthetic(self, synthetic_calib):
        calib = load_calibration_set(synthetic_calib, (240, 320))
        assert len(calib.presses) == 6
        assert calib.shape == (240, 320)
        assert calib.background.dtype == np.float32
        img = calib.image(calib.presses[0])
        assert img.shape == (240, 320, 3) and img.dtype == np.uint8

    def test_real_folder(self, mini_calib):
        assert len(mini_calib.presses) == 59
        assert {p.diameter_mm for p in mini_calib.presses} == {6.31, 9.5}
        assert mini_calib.press("9.500mm/0").ball_radius_px(0.0634) == pytest.approx(74.92, abs=0.01)

    def test_fingerprint_tracks_content(self, synthetic_calib):
        a = load_calibration_set(synthetic_calib).fingerprint()
        assert a == load_calibration_set(synthetic_calib).fingerprint() and len(a) == 16
        img = cv2.imread(str(synthetic_calib / "6.310mm/0/gelsight.png"))
        img[0, 0] ^= 1
        cv2.imwrite(str(synthetic_calib / "6.310mm/0/gelsight.png"), img)
        assert load_calibration_set(synthetic_calib).fingerprint() != a

    def test_missing_folder(self, tmp_path):
        with pytest.raises(CalibrationDataError, match="folder not found"):
            load_calibration_set(tmp_path / "nope")

    def test_no_catalog(self, synthetic_calib):
        (synthetic_calib / "catalog.csv").unlink()
        with pytest.raises(CalibrationDataError, match="catalog not found"):
            load_calibration_set(synthetic_calib)

    def test_missing_image(self, synthetic_calib):
        shutil.rmtree(synthetic_calib / "9.500mm/1")
        with pytest.raises(CalibrationDataError, match="missing.*9.500mm/1"):
            load_calibration_set(synthetic_calib)

    def test_missing_background(self, synthetic_calib):
        (synthetic_calib / "background.png").unlink()
        with pytest.raises(CalibrationDataError, match="background.png"):
            load_calibration_set(synthetic_calib)

    def test_wrong_image_size(self, synthetic_calib):
        cv2.imwrite(str(synthetic_calib / "6.310mm/2/gelsight.png"), np.zeros((120, 160, 3), np.uint8))
        with pytest.raises(CalibrationDataError, match="6.310mm/2.*160x120"):
            load_calibration_set(synthetic_calib)

    def test_wrong_sensor_size(self, synthetic_calib):
        """A whole set at another size than the config's: the error says which config it needs."""
        with pytest.raises(CalibrationDataError, match="is 320x240.*expected 640x480.*width 320, height 240"):
            load_calibration_set(synthetic_calib, (480, 640))

    def test_undecodable_image(self, synthetic_calib):
        (synthetic_calib / "6.310mm/0/gelsight.png").write_bytes(b"not a png")
        with pytest.raises(CalibrationDataError, match="cannot decode"):
            load_calibration_set(synthetic_calib)


class TestReadCatalog:
    @pytest.mark.parametrize(
        "text, match",
        [
            ("dir,diam\n6.310mm/0,6.31\n", "header"),
            ("experiment_reldir,diameter(mm)\n", "no presses"),
            ("experiment_reldir,diameter(mm)\n6.310mm/0,abc\n", "not a number"),
            ("experiment_reldir,diameter(mm)\n6.310mm/0,-1\n", "> 0"),
            ("experiment_reldir,diameter(mm)\n6.310mm/0,nan\n", "> 0"),
            ("experiment_reldir,diameter(mm)\n6.310mm/0,6.31\n6.310mm/0,6.31\n", "twice"),
            ("experiment_reldir,diameter(mm)\n6.310mm/0\n", "2 columns"),
            ("experiment_reldir,note,diameter(mm)\n6.310mm/0,x,6.31\n", "header"),
        ],
    )
    def test_bad_catalog(self, tmp_path, text, match):
        (tmp_path / "catalog.csv").write_text(text)
        with pytest.raises(CalibrationDataError, match=match):
            read_catalog(tmp_path / "catalog.csv")

    def test_rows(self, tmp_path):
        (tmp_path / "catalog.csv").write_text("experiment_reldir,diameter(mm)\n6.310mm/0,6.31\n\n9.500mm/3,9.5\n")
        assert read_catalog(tmp_path / "catalog.csv") == [("6.310mm/0", 6.31), ("9.500mm/3", 9.5)]

    @pytest.mark.parametrize(
        "text",
        [
            "\ufeffexperiment_reldir,diameter(mm)\r\n6.310mm/0,6.31\r\n9.500mm/3,9.5\r\n",  # BOM, CRLF
            "experiment_reldir,diameter(mm),\n6.310mm/0,6.31,\n9.500mm/3,9.5,,\n",  # trailing commas
            "experiment_reldir,diameter(mm),note\n6.310mm/0,6.31,first\n9.500mm/3,9.5,x,y\n",  # extra columns
            "experiment_reldir,diameter(mm)\n6.310mm\\0,6.31\n9.500mm\\3,9.5\n",  # Windows paths
        ],
    )
    def test_lenient_formats(self, tmp_path, text):
        """Files written by spreadsheets and on Windows: all were rejected (or kept the
        BOM in the header, or a backslash in the path) before 2026-12-03."""
        (tmp_path / "catalog.csv").write_text(text, encoding="utf-8", newline="")
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            assert read_catalog(tmp_path / "catalog.csv") == [("6.310mm/0", 6.31), ("9.500mm/3", 9.5)]

    @pytest.mark.parametrize("row", ["9.500mm/5,6.31", "6.310mm/7,63.1", "6mm/1,6.7"])
    def test_diameter_that_contradicts_the_folder_warns(self, tmp_path, row):
        (tmp_path / "catalog.csv").write_text(f"experiment_reldir,diameter(mm)\n6.310mm/0,6.31\n{row}\n")
        with pytest.warns(CatalogWarning, match=f"1 press folder.*{row.split(',')[0]} listed as"):
            assert len(read_catalog(tmp_path / "catalog.csv")) == 2

    @pytest.mark.parametrize("row", ["6.31mm/1,6.31", "6mm/1,6.31", "6.310mm/1,6.3104", "ball_a/1,9.5"])
    def test_matching_or_unnamed_folders_do_not_warn(self, tmp_path, row):
        (tmp_path / "catalog.csv").write_text(f"experiment_reldir,diameter(mm)\n{row}\n")
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            read_catalog(tmp_path / "catalog.csv")
