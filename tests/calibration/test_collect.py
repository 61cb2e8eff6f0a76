import numpy as np
import pytest

from tactile_slam.calibration.catalog import CalibrationDataError, load_calibration_set
from tactile_slam.calibration.collect import CollectPlan, collect_calibration
from tactile_slam.calibration.labels import label_presses

from .conftest import MM_PER_PX, press_image, render, synthetic_background


class FakeCamera:
    """Serves frames from a list (background frames first, then one per press), then
    fails like a disconnected sensor."""

    def __init__(self, frames):
        self.frames = list(frames)

    def __call__(self):
        if not self.frames:
            raise ValueError("read failed (sensor disconnected?)")
        return self.frames.pop(0)


def _plan(**kw):
    base = dict(diameters_mm=(6.31,), presses_per_ball=2, shape=(240, 320), mm_per_px=MM_PER_PX,
                background_frames=3)
    base.update(kw)
    return CollectPlan(**base)


def test_guided_session_writes_a_loadable_folder(tmp_path):
    bg = synthetic_background()
    flat = [render(bg, np.zeros((240, 320, 2)), seed=i) for i in range(3)]
    presses = [press_image(100, 90, 25, 6.31, seed=5), press_image(210, 150, 26, 6.31, seed=6)]
    prompts, said = [], []
    cat = collect_calibration(tmp_path / "c", FakeCamera(flat + presses), _plan(),
                              prompt=lambda m: prompts.append(m) or "", say=said.append)
    assert cat.read_text().splitlines() == ["experiment_reldir,diameter(mm)", "6.310mm/0,6.31", "6.310mm/1,6.31"]
    assert len(prompts) == 3 and "background" in prompts[0]
    calib = load_calibration_set(tmp_path / "c", (240, 320))
    labels = label_presses(calib, MM_PER_PX, 2.0)
    assert abs(labels[1].cx - 210) < 1 and abs(labels[1].radius - 26) < 1.5


def test_press_without_contact_is_asked_again(tmp_path):
    bg = synthetic_background()
    flat = [render(bg, np.zeros((240, 320, 2)), seed=i) for i in range(4)]
    frames = flat[:3] + [flat[3], press_image(100, 90, 25, 6.31, seed=5)]
    prompts = []
    collect_calibration(tmp_path / "c", FakeCamera(frames), _plan(presses_per_ball=1),
                        prompt=lambda m: prompts.append(m) or "", say=lambda m: None)
    assert any("no contact visible" in p for p in prompts)
    assert (tmp_path / "c" / "6.310mm/0/gelsight.png").exists()


def test_gives_up_after_retries(tmp_path):
    bg = synthetic_background()
    flat = [render(bg, np.zeros((240, 320, 2)), seed=i) for i in range(8)]
    with pytest.raises(CalibrationDataError, match="no contact visible in 3 tries"):
        collect_calibration(tmp_path / "c", FakeCamera(flat), _plan(presses_per_ball=1),
                            prompt=lambda m: "", say=lambda m: None)


def test_quit_and_errors(tmp_path):
    bg = synthetic_background()
    flat = [render(bg, np.zeros((240, 320, 2)), seed=i) for i in range(3)]
    with pytest.raises(CalibrationDataError, match="no press was recorded"):
        collect_calibration(tmp_path / "a", FakeCamera(flat), _plan(), prompt=lambda m: "q", say=lambda m: None)
    with pytest.raises(ValueError, match="disconnected"):
        collect_calibration(tmp_path / "b", FakeCamera([]), _plan(), prompt=lambda m: "", say=lambda m: None)
    with pytest.raises(CalibrationDataError, match="must be BGR"):
        collect_calibration(tmp_path / "e", FakeCamera([np.zeros((10, 10, 3), np.uint8)]), _plan(),
                            prompt=lambda m: "", say=lambda m: None)
    (tmp_path / "d").mkdir()
    (tmp_path / "d" / "catalog.csv").write_text("x")
    with pytest.raises(CalibrationDataError, match="already holds"):
        collect_calibration(tmp_path / "d", FakeCamera(flat), _plan(), prompt=lambda m: "", say=lambda m: None)
