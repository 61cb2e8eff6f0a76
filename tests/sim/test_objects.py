import warnings

import numpy as np
import open3d as o3d
import pytest

from tactile_slam.sim.objects import (OBJECTS, MeshSizeWarning, ObjectError, extent_mm, load_object, make_object,
                                      resolve_object)

COARSE = 0.4  # mm; the topology and sizes do not depend on the resolution


def closed_consistent(mesh) -> bool:
    """Every directed edge appears once and its reverse once: a closed, consistently
    wound surface (open3d's is_watertight adds an O(n^2)-ish self-intersection test)."""
    tri = np.asarray(mesh.triangles).astype(np.int64)
    e = np.concatenate([tri[:, [0, 1]], tri[:, [1, 2]], tri[:, [2, 0]]])
    n = len(mesh.vertices)
    key, rev = e[:, 0] * n + e[:, 1], e[:, 1] * n + e[:, 0]
    return len(np.unique(key)) == len(key) and bool(np.isin(rev, key).all())


@pytest.mark.parametrize("name", sorted(OBJECTS))
def test_objects_watertight_metres_and_sized(name):
    mesh = make_object(name, resolution_mm=COARSE)
    assert closed_consistent(mesh)
    assert mesh.has_vertex_normals()
    ext = np.asarray(mesh.get_axis_aligned_bounding_box().get_extent()) * 1000.0
    size = OBJECTS[name].default_size_mm
    # the largest extent is the object's size (plane: 30 mm square; handle/knurled: longer axis)
    assert size * 0.9 <= ext.max() <= 2.2 * size
    assert ext.max() < 100  # metres, not mm


@pytest.mark.parametrize("name", ["seed", "shell", "dice", "lime", "knurled", "plane"])
def test_texture_relief_in_tactile_range(name):
    """Displacement from the base shape: 0.05-0.5 mm relief (same icosphere topology)."""
    spec = OBJECTS[name]
    base_pts, _, _ = spec.shape(spec.default_size_mm).mesh(COARSE)
    mesh = make_object(name, resolution_mm=COARSE)
    disp = np.linalg.norm(np.asarray(mesh.vertices) * 1000.0 - base_pts, axis=1)
    assert 0.05 <= disp.max() <= 0.5


def test_ball_is_textureless_and_handle_faint():
    spec = OBJECTS["ball"]
    base, _, _ = spec.shape(spec.default_size_mm).mesh(COARSE)
    assert np.allclose(np.asarray(make_object("ball", resolution_mm=COARSE).vertices) * 1000, base, atol=1e-9)
    spec = OBJECTS["handle"]
    base, _, _ = spec.shape(spec.default_size_mm).mesh(COARSE)
    disp = np.linalg.norm(np.asarray(make_object("handle", resolution_mm=COARSE).vertices) * 1000 - base, axis=1)
    assert 0.005 < disp.max() < 0.06


def test_outward_winding():
    mesh = make_object("dice", resolution_mm=COARSE)
    mesh.compute_triangle_normals()
    centres = np.asarray(mesh.vertices)[np.asarray(mesh.triangles)].mean(axis=1)
    assert (np.sum(np.asarray(mesh.triangle_normals) * centres, axis=1) > 0).mean() > 0.99
    assert o3d.geometry.TriangleMesh(mesh).get_volume() > 0


def test_deterministic_for_seed_and_fresh_copies():
    a = make_object("lime", seed=3, resolution_mm=COARSE)
    b = make_object("lime", seed=3, resolution_mm=COARSE)
    c = make_object("lime", seed=4, resolution_mm=COARSE)
    assert np.array_equal(np.asarray(a.vertices), np.asarray(b.vertices))
    assert not np.array_equal(np.asarray(a.vertices), np.asarray(c.vertices))
    a.translate([1.0, 0, 0])  # a copy: the cache is untouched
    again = make_object("lime", seed=3, resolution_mm=COARSE)
    assert np.array_equal(np.asarray(again.vertices), np.asarray(b.vertices))


def test_size_argument_scales():
    ext = np.asarray(make_object("ball", size_mm=10, resolution_mm=COARSE).get_axis_aligned_bounding_box().get_extent())
    assert np.allclose(ext * 1000, 10, atol=0.05)


def test_errors():
    with pytest.raises(ObjectError, match="unknown object"):
        make_object("teapot")
    with pytest.raises(ObjectError, match="size"):
        make_object("ball", size_mm=float("nan"))
    with pytest.raises(ObjectError, match="resolution"):
        make_object("ball", resolution_mm=0)
    with pytest.raises(ObjectError, match="not found"):
        load_object("/nonexistent/mesh.ply")
    with pytest.raises(ObjectError, match="unknown object"):
        resolve_object("teapot")


def test_load_user_mesh_with_scale(tmp_path):
    box = o3d.geometry.TriangleMesh.create_box(10, 20, 30)  # "mm"
    path = tmp_path / "box.stl"
    box.compute_triangle_normals()
    o3d.io.write_triangle_mesh(str(path), box)
    mesh = resolve_object(str(path), scale=1e-3)
    assert np.allclose(np.asarray(mesh.get_axis_aligned_bounding_box().get_extent()), [0.01, 0.02, 0.03])
    bad = tmp_path / "mesh.xyz"
    bad.write_text("0 0 0\n")
    with pytest.raises(ObjectError, match="unsupported"):
        load_object(bad)


def _sphere_file(path, radius):
    o3d.io.write_triangle_mesh(str(path), o3d.geometry.TriangleMesh.create_sphere(radius, resolution=20))
    return path


def test_user_mesh_outside_tactile_sizes_warns_of_its_units(tmp_path):
    """A 12 mm sphere saved in mm became a 12 m object without a word, and a 1 mm one an
    episode without contact: both warn, naming the size and the scale to give."""
    in_mm = _sphere_file(tmp_path / "sphere_mm.ply", 6.0)
    with pytest.warns(MeshSizeWarning, match=r"1\.2e\+04 mm across.*--mesh-scale"):
        mesh = load_object(in_mm)
    assert extent_mm(mesh) == pytest.approx(12_000, rel=1e-3)
    with pytest.warns(MeshSizeWarning, match=r"1 mm across.*outside the 2-200 mm"):
        load_object(_sphere_file(tmp_path / "tiny.ply", 0.0005))
    with warnings.catch_warnings():
        warnings.simplefilter("error", MeshSizeWarning)  # in range once scaled: silent
        assert extent_mm(load_object(in_mm, scale=1e-3)) == pytest.approx(12.0, rel=1e-3)


def test_a_flag_for_the_other_kind_of_object_is_refused(tmp_path):
    """--size-mm on a mesh file and --mesh-scale on a catalogue object were ignored while
    meta.yaml recorded them as applied."""
    path = _sphere_file(tmp_path / "sphere.ply", 0.006)
    with pytest.raises(ObjectError, match=r"--size-mm\) applies to catalogue objects.*sphere\.ply"):
        resolve_object(str(path), size_mm=30.0)
    with pytest.raises(ObjectError, match=r"--mesh-scale\) applies to mesh files.*'seed'"):
        resolve_object("seed", scale=1e-3)
    assert extent_mm(resolve_object(str(path), scale=2.0)) == pytest.approx(24.0, rel=1e-3)
