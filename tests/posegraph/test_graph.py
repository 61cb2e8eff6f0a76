"""PoseGraph construction, validation and g2o round trip."""

from __future__ import annotations

import pytest
import torch

from tactile_slam.config import PoseGraphConfig
from tactile_slam.posegraph import se3
from tactile_slam.posegraph.graph import GraphError, PoseGraph
from tactile_slam.posegraph.synthetic import synthetic_scan


def _pose(*xi: float) -> torch.Tensor:
    return se3.exp(torch.tensor(xi, dtype=torch.float64))


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
