import numpy as np
import open3d as o3d
import pytest

from tactile_slam.eval.recon_metrics import ReconMetricError, icp_refine, ncd, recon_report, surface_metrics
from tactile_slam.sim.objects import make_object


@pytest.fixture(scope="module")
def ball():
    return make_object("ball", resolution_mm=0.15)


def scaled(mesh, factor):
    out = o3d.geometry.TriangleMesh(mesh)
    out.vertices = o3d.utility.Vector3dVector(np.asarray(mesh.vertices) * factor)
    return out


def test_identical_meshes(ball):
    m = surface_metrics(ball, ball, 20000)
    assert m["chamfer_mm"] < 1e-4
    assert all(v["f"] == 1.0 for v in m["fscore"].values())
    assert m["normal_consistency"] == pytest.approx(1.0)


def test_offset_sphere_is_offset_distance(ball):
    """A concentric sphere 0.1 mm larger: every point is 0.1 mm from the other surface."""
    m = surface_metrics(scaled(ball, 10.1 / 10.0), ball, 20000)
    assert m["chamfer_mm"] == pytest.approx(0.1, abs=0.002)
    m = surface_metrics(scaled(ball, 10.2 / 10.0), ball, 20000)
    assert m["fscore"]["0.1"]["f"] == 0.0 and m["fscore"]["0.25"]["f"] == 1.0


def test_translated_sphere_is_half_the_shift(ball):
    """Shifted by 0.1 mm: a point at polar angle theta is 0.1 |cos theta| mm from the other
    sphere (to first order), whose mean over the sphere is 0.1 / 2 mm."""
    m = surface_metrics(o3d.geometry.TriangleMesh(ball).translate([1e-4, 0, 0]), ball, 40000)
    assert m["chamfer_mm"] == pytest.approx(0.05, abs=0.002)


def test_ncd_identical_and_degraded():
    seed = make_object("seed", resolution_mm=0.1)
    assert ncd(seed, seed, n_touches=6)["ncd"] == pytest.approx(1.0, abs=1e-6)
    other = make_object("seed", resolution_mm=0.1, seed=1)  # same shape, other bumps
    res = ncd(other, seed, n_touches=6)
    assert res["touches_used"] == 6 and res["ncd"] < 0.9995


def test_report_places_reconstruction_with_gt_pose_and_icp_refines():
    seed = make_object("seed", resolution_mm=0.1)
    object_T_start = np.eye(4)
    object_T_start[:3, 3] = [0.001, -0.002, 0.003]
    recon = o3d.geometry.TriangleMesh(seed).transform(np.linalg.inv(object_T_start))
    rep = recon_report(recon, seed, object_T_start, icp=False, n_samples=20000, n_touches=4)
    assert rep["gt_pose"]["chamfer_mm"] < 1e-4 and rep["gt_pose"]["ncd"] == pytest.approx(1.0, abs=1e-6)
    nudged = o3d.geometry.TriangleMesh(seed).translate([2e-4, 0, 0])
    corr = icp_refine(nudged, seed)
    assert np.allclose(corr[:3, 3], [-2e-4, 0, 0], atol=2e-5)


def test_errors(ball):
    with pytest.raises(ReconMetricError, match="no triangles"):
        surface_metrics(o3d.geometry.TriangleMesh(), ball)
