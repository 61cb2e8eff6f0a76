"""PoseGraph construction, validation and g2o round trip."""

from __future__ import annotations

import math
import re

import pytest
import torch

from tactile_slam.config import PoseGraphConfig
from tactile_slam.posegraph import se3
from tactile_slam.posegraph.graph import GraphError, PoseGraph
from tactile_slam.posegraph.synthetic import synthetic_scan


def _pose(*xi: float) -> torch.Tensor:
    return se3.exp(torch.tensor(xi, dtype=torch.float64))


def _upper_of_diag(d: float) -> str:
    """The 21 upper-triangular g2o entries of the information ``d * I``."""
    return " ".join(str(d) if i == j else "0" for i in range(6) for j in range(i, 6))


_INFO_1, _INFO_100 = _upper_of_diag(1), _upper_of_diag(100)


class TestPoseGraph:
    def test_smoke(self):
        g = PoseGraph()
        g.add_node(10)
        g.add_node(11, _pose(1e-3, 0, 0, 0, 0, 0.1))
        g.add_prior(10)
        k = g.add_between(10, 11, _pose(1e-3, 0, 0, 0, 0, 0.1), kind="loop")
        assert (g.num_nodes, g.num_edges, k) == (2, 1, 0)
        assert g.ids.tolist() == [10, 11]
        assert g.edges.loop.tolist() == [True]
        assert torch.allclose(g.pose(11), _pose(1e-3, 0, 0, 0, 0, 0.1))
        assert g.has_prior(10) and not g.has_prior(11)
        g.remove_prior(10)
        assert g.priors.rows.numel() == 0

    def test_default_and_explicit_sigma(self):
        g = PoseGraph(PoseGraphConfig(sigma_rot_rad=0.02, sigma_trans_m=2e-4))
        g.add_nodes([0, 1, 2], torch.eye(4, dtype=torch.float64).expand(3, 4, 4))
        g.add_between(0, 1, torch.eye(4))
        g.add_between(1, 2, torch.eye(4), sigma=[1e-3] * 3 + [0.5] * 3)
        s = g.edges.sigma
        assert torch.allclose(s[0], torch.tensor([2e-4] * 3 + [0.02] * 3, dtype=torch.float64))
        assert torch.allclose(s[1], torch.tensor([1e-3] * 3 + [0.5] * 3, dtype=torch.float64))

    def test_batched_adds_cardinality(self):
        g = PoseGraph()
        n = 40  # crosses the initial buffer capacity
        g.add_nodes(range(n), se3.exp(torch.randn(n, 6, dtype=torch.float64) * 0.1))
        idx = g.add_betweens(list(range(n - 1)), list(range(1, n)), torch.eye(4).expand(n - 1, 4, 4))
        assert idx == list(range(n - 1))
        assert g.edges.Z.shape == (n - 1, 4, 4) and g.poses().shape == (n, 4, 4)
        assert g.poses([3, 5]).shape == (2, 4, 4)

    def test_errors(self):
        g = PoseGraph()
        g.add_node(0)
        with pytest.raises(GraphError, match="already"):
            g.add_node(0)
        with pytest.raises(GraphError, match="node 7 is not in"):
            g.add_between(0, 7, torch.eye(4))
        with pytest.raises(GraphError, match="itself"):
            g.add_node(1) or g.add_between(1, 1, torch.eye(4))
        with pytest.raises(GraphError, match="kind"):
            g.add_between(0, 1, torch.eye(4), kind="odo")
        with pytest.raises(GraphError, match="sigma"):
            g.add_between(0, 1, torch.eye(4), sigma=[0.0, 1.0])
        with pytest.raises(GraphError, match="sigma must have"):
            g.add_between(0, 1, torch.eye(4), sigma=[1.0, 1.0, 1.0])
        with pytest.raises(GraphError, match=r"\(4, 4\)"):
            g.add_between(0, 1, torch.eye(3))
        with pytest.raises(ValueError, match="NaN"):
            g.add_between(0, 1, torch.full((4, 4), float("nan")))
        with pytest.raises(GraphError, match="no prior"):
            g.remove_prior(0)
        with pytest.raises(GraphError, match="not in"):
            g.add_prior(5)
        with pytest.raises(GraphError, match="not in"):
            g.pose(5)

    def test_set_poses_checks_rows_and_poses(self):
        """set_poses used to write anything: a scaled rotation (det 8) then passed through a
        solve unchanged with converged=True, and a NaN pose reached the solver."""
        g = PoseGraph()
        g.add_nodes([0, 1, 2], torch.eye(4, dtype=torch.float64).expand(3, 4, 4))
        before = g.poses()
        scaled = torch.eye(4, dtype=torch.float64)
        scaled[:3, :3] *= 2
        with pytest.raises(se3.PoseError, match="not orthonormal"):
            g.set_poses(torch.tensor([1]), scaled[None])
        with pytest.raises(se3.PoseError, match="NaN"):
            g.set_poses(torch.tensor([1]), torch.full((1, 4, 4), float("nan"), dtype=torch.float64))
        with pytest.raises(GraphError, match=re.escape("rows [3] are outside the graph's rows 0..2")):
            g.set_poses(torch.tensor([3]), torch.eye(4, dtype=torch.float64)[None])
        with pytest.raises(GraphError, match=re.escape("rows [-1] are outside")):
            g.set_poses(torch.tensor([-1]), torch.eye(4, dtype=torch.float64)[None])
        with pytest.raises(GraphError, match=r"must be \(2, 4, 4\)"):
            g.set_poses([0, 1], torch.eye(4, dtype=torch.float64)[None])
        with pytest.raises(GraphError, match="integers"):
            g.set_poses(torch.tensor([1.0]), torch.eye(4, dtype=torch.float64)[None])
        assert torch.equal(g.poses(), before)
        g.set_poses([2], _pose(1e-3, 0, 0, 0, 0, 0.1)[None])
        assert torch.allclose(g.pose(2), _pose(1e-3, 0, 0, 0, 0, 0.1))

    @pytest.mark.parametrize("sigma", [1e-200, 1e-155, 1e154, 1e200])
    def test_sigma_whose_information_leaves_float64_is_refused(self, sigma):
        """sigma 1e-200 was accepted: its information 1e400 is inf in float64, the solver's cost
        was inf and the g2o file it wrote could not be read back (1e200 underflowed to 0)."""
        g = PoseGraph()
        g.add_nodes([0, 1], torch.eye(4, dtype=torch.float64).expand(2, 4, 4))
        with pytest.raises(GraphError, match="information sigma\\^-2 is a finite, normal float64"):
            g.add_between(0, 1, torch.eye(4), sigma=[sigma, sigma])
        with pytest.raises(GraphError, match="information"):
            g.add_prior(0, sigma=[sigma] * 6)


class TestG2o:
    def test_round_trip(self, tmp_path):
        scan = synthetic_scan(60, 20, n_sessions=2, seed=3, radius_m=0.005)
        g = scan.graph
        g.add_between(0, 30, scan.gt[0].inverse() @ scan.gt[30], sigma=[1e-3] * 3 + [0.2] * 3, kind="loop")
        path = g.to_g2o(tmp_path / "graph.g2o")
        text = path.read_text()
        assert text.count("VERTEX_SE3:QUAT") == 60 and text.count("EDGE_SE3_PRIOR") == 2
        h = PoseGraph.from_g2o(path)
        assert h.ids.tolist() == g.ids.tolist()
        assert torch.allclose(h.poses(), g.poses(), atol=1e-12)
        order_g = torch.argsort(g.edges.i * 1000 + g.edges.j)
        order_h = torch.argsort(h.edges.i * 1000 + h.edges.j)
        for name in ("i", "j", "loop"):
            assert torch.equal(getattr(g.edges, name)[order_g], getattr(h.edges, name)[order_h])
        assert torch.allclose(g.edges.Z[order_g], h.edges.Z[order_h], atol=1e-12)
        assert torch.allclose(g.edges.sigma[order_g], h.edges.sigma[order_h], rtol=1e-12)
        assert torch.equal(g.priors.rows, h.priors.rows)

    def test_foreign_file_kinds_by_consecutive_ids(self, tmp_path):
        info = " ".join(["1"] + ["0"] * 5 + ["1"] + ["0"] * 4 + ["1"] + ["0"] * 3 + ["1", "0", "0", "1", "0", "1"])
        lines = [f"VERTEX_SE3:QUAT {k} 0 0 0 0 0 0 1" for k in range(3)]
        lines += [f"EDGE_SE3:QUAT 0 1 0 0 0 0 0 0 1 {info}", f"EDGE_SE3:QUAT 0 2 0 0 0 0 0 0 1 {info}"]
        p = tmp_path / "f.g2o"
        p.write_text("\n".join(lines))
        g = PoseGraph.from_g2o(p)
        assert g.edges.loop.tolist() == [False, True]

    def test_errors(self, tmp_path):
        with pytest.raises(GraphError, match="not found"):
            PoseGraph.from_g2o(tmp_path / "missing.g2o")
        p = tmp_path / "bad.g2o"
        p.write_text("VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1\nFOO 1 2\n")
        with pytest.raises(GraphError, match="bad.g2o:2"):
            PoseGraph.from_g2o(p)
        p.write_text("VERTEX_SE3:QUAT 0 0 0 0 0 0 0 0\n")
        with pytest.raises(GraphError, match="quaternion"):
            PoseGraph.from_g2o(p)

    def test_written_file_is_g2o_readable(self, tmp_path):
        """g2o's EDGE_SE3_PRIOR reads a parameter id after the vertex id, defined by a
        PARAMS_SE3OFFSET record; the prior used to be written without either."""
        g = PoseGraph()
        g.add_nodes([0, 1], torch.stack([torch.eye(4, dtype=torch.float64), _pose(1e-3, 0, 0, 0, 0, 0.1)]))
        g.add_prior(0, _pose(0, 2e-3, 0, 0, 0, 0), sigma=[1e-150] * 6)
        g.add_between(0, 1, _pose(1e-3, 0, 0, 0, 0, 0.1))
        lines = g.to_g2o(tmp_path / "g.g2o").read_text().splitlines()
        assert lines[0].split() == ["PARAMS_SE3OFFSET", "0"] + ["0.0"] * 6 + ["1.0"]
        prior = next(line.split() for line in lines if line.startswith("EDGE_SE3_PRIOR"))
        assert len(prior) == 31 and prior[1:3] == ["0", "0"] and prior[4] == "0.002"
        values = [float(t) for line in lines for t in line.split()[1:]]
        assert all(math.isfinite(v) for v in values)  # sigma 1e-150: information 1e300
        h = PoseGraph.from_g2o(tmp_path / "g.g2o")
        assert torch.allclose(h.priors.Z, g.priors.Z, atol=1e-15)
        assert torch.allclose(h.priors.sigma, g.priors.sigma, rtol=1e-12)

    def test_reads_the_earlier_prior_form(self, tmp_path):
        """Files written before the parameter id (a 30-token EDGE_SE3_PRIOR) still load."""
        p = tmp_path / "old.g2o"
        p.write_text(f"VERTEX_SE3:QUAT 3 0 0 0 0 0 0 1\nEDGE_SE3_PRIOR 3 0.001 0 0 0 0 0 1 {_INFO_100}\n")
        g = PoseGraph.from_g2o(p)
        assert g.has_prior(3)
        assert torch.allclose(g.priors.Z[0], _pose(1e-3, 0, 0, 0, 0, 0))
        assert torch.allclose(g.priors.sigma[0], torch.full((6,), 0.1, dtype=torch.float64))

    def test_reads_fix_and_identity_offsets(self, tmp_path):
        """FIX anchors a vertex: a prior at its value with the default sigma, replacing its own
        prior; a prior may refer to an identity PARAMS_SE3OFFSET. Both used to be refused."""
        p = tmp_path / "fix.g2o"
        p.write_text("\n".join([
            "PARAMS_SE3OFFSET 4 0 0 0 0 0 0 1",
            "VERTEX_SE3:QUAT 0 0.002 0 0 0 0 0 1",
            "VERTEX_SE3:QUAT 1 0.003 0 0 0 0 0 1",
            "VERTEX_SE3:QUAT 2 0.004 0 0 0 0 0 1",
            "FIX 0",
            f"EDGE_SE3_PRIOR 0 4 0 0 0 0 0 0 1 {_INFO_100}",
            f"EDGE_SE3_PRIOR 2 4 0.005 0 0 0 0 0 1 {_INFO_100}",
            f"EDGE_SE3:QUAT 0 1 0.001 0 0 0 0 0 1 {_INFO_100}",
        ]) + "\n")
        g = PoseGraph.from_g2o(p)
        assert g.priors.rows.tolist() == [0, 2]
        assert torch.allclose(g.priors.Z[0], _pose(2e-3, 0, 0, 0, 0, 0))  # FIX: at the vertex
        assert torch.equal(g.priors.sigma[0], g.default_sigma)
        assert torch.allclose(g.priors.Z[1], _pose(5e-3, 0, 0, 0, 0, 0))  # the file's prior
        assert torch.allclose(g.priors.sigma[1], torch.full((6,), 0.1, dtype=torch.float64))

    @pytest.mark.parametrize("records, message", [
        (["PARAMS_SE3OFFSET 1 0.1 0 0 0 0 0 1"], "3: PARAMS_SE3OFFSET 1 is not the identity"),
        (["PARAMS_SE3OFFSET 1 0 0 0 0 0 0 1"] * 2, "4: parameter 1 is already defined"),
        ([f"EDGE_SE3_PRIOR 0 1 0 0 0 0 0 0 1 {_INFO_100}"], "3: EDGE_SE3_PRIOR refers to parameter 1"),
        (["FIX 0 5"], "3: node 5 is not in the pose graph"),
        ([f"EDGE_SE3:QUAT 0 7 0 0 0 0 0 0 1 {_INFO_100}"], "3: node 7 is not in the pose graph"),
        ([f"EDGE_SE3:QUAT 0 1 0 0 0 0 0 0 1 inf {_INFO_100[4:]}"], "3: information matrix has non-finite"),
        ([f"EDGE_SE3:QUAT 0 1 0 0 0 0 0 0 1 1 10 {_INFO_1[4:]}"], "3: information matrix is not positive definite"),
        ([f"EDGE_SE3:QUAT 0 1 0 0 0 0 0 0 1 1e-320 {_INFO_1[2:]}"], "3: sigma must lie within"),
    ])
    def test_bad_records_name_file_and_line(self, tmp_path, records, message):
        """A missing vertex or an inf information entry used to raise without the file and line;
        an indefinite information matrix with a positive diagonal used to be read."""
        p = tmp_path / "bad.g2o"
        p.write_text("\n".join(["VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1", "VERTEX_SE3:QUAT 1 0 0 0 0 0 0 1"] + records) + "\n")
        with pytest.raises(GraphError, match=re.escape(f"bad.g2o:{message}")):
            PoseGraph.from_g2o(p)

    def test_correlated_information_keeps_its_diagonal(self, tmp_path):
        """A positive-definite information matrix with off-diagonal entries is read by its
        diagonal (noise is diagonal here; docs/posegraph.md)."""
        info = 100 * torch.eye(6, dtype=torch.float64)
        info[0, 3] = info[3, 0] = 99
        upper = " ".join(repr(v) for v in info[torch.triu_indices(6, 6).unbind()].tolist())
        p = tmp_path / "corr.g2o"
        p.write_text(f"VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1\nVERTEX_SE3:QUAT 1 0 0 0 0 0 0 1\n"
                     f"EDGE_SE3:QUAT 0 1 0 0 0 0 0 0 1 {upper}\n")
        assert torch.allclose(PoseGraph.from_g2o(p).edges.sigma[0], torch.full((6,), 0.1, dtype=torch.float64))
