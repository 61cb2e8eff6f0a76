import numpy as np
import pytest

from tactile_slam.sim.heldout import SHAPES, make_heldout, plane_waves, write_heldout
from tactile_slam.sim.objects import OBJECTS, load_object
from tests.sim.test_objects import closed_consistent

COARSE = 0.4  # mm


@pytest.mark.parametrize("name", SHAPES)
def test_heldout_closed_outward_and_sized(name):
    mesh = make_heldout(name, COARSE)
    assert closed_consistent(mesh)
    assert mesh.get_volume() > 0  # outward winding
    ext = np.asarray(mesh.get_axis_aligned_bounding_box().get_extent()) * 1000.0
    expected = {"torus": (26.0, 26.0, 8.0), "screw": (10.0, 10.0, 22.0), "rock": (20.0, 20.0, 20.0)}[name]
    np.testing.assert_allclose(ext, expected, rtol=0.2)


def test_heldout_names_are_not_catalogue_objects():
    assert not set(SHAPES) & set(OBJECTS)


def test_torus_has_saddles_and_screw_a_thread():
    torus = np.asarray(make_heldout("torus", COARSE).vertices) * 1000.0
    ring = np.hypot(torus[:, 0], torus[:, 1])
    assert ring.min() < 5.5 and ring.max() > 12.5  # the hole (9 - 4) and the rim (9 + 4), with relief
    screw = np.asarray(make_heldout("screw", 0.1).vertices) * 1000.0
    mid = np.abs(screw[:, 2]) < 5.0
    r = np.hypot(screw[mid, 0], screw[mid, 1])
    assert 4.6 < r.min() < 4.8 and r.max() == pytest.approx(5.0, abs=0.02)  # 0.3 mm deep thread


def test_plane_waves_amplitude_scales_with_wavelength():
    rng = np.random.default_rng(0)
    p = np.random.default_rng(1).uniform(-50, 50, (20000, 3))
    a = plane_waves(p, rng, 1, (2.0, 2.0), 0.01)
    assert np.abs(a).max() == pytest.approx(0.02, rel=1e-3)


def test_write_heldout_loads_as_a_user_mesh(tmp_path):
    (path,) = write_heldout(tmp_path, ("rock",), resolution_mm=0.5, seed=3)
    mesh = load_object(path)
    np.testing.assert_allclose(np.asarray(mesh.vertices), np.asarray(make_heldout("rock", 0.5, 3).vertices),
                               atol=1e-9)
    assert not np.allclose(np.asarray(make_heldout("rock", 0.5, 4).vertices), np.asarray(mesh.vertices))


def test_heldout_bad_input():
    with pytest.raises(ValueError, match="unknown held-out shape"):
        make_heldout("seed")
    with pytest.raises(ValueError, match="resolution_mm"):
        make_heldout("torus", 0.0)
