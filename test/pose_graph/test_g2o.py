"""g2o files: bit-exact round trip of a 2D graph, malformed files."""

from __future__ import annotations

import numpy as np
import pytest

from linear_slam_ros.core.errors import GraphError
from linear_slam_ros.pose_graph.g2o import read_g2o, write_g2o
from linear_slam_ros.pose_graph.graph import PoseGraph


def test_g2o_round_trip_and_errors(tmp_path, rng, circle_graph):
    _, graph = circle_graph(rng, sigma=(0.01, 0.002))
    write_g2o(tmp_path / "g.g2o", graph)
    back = read_g2o(tmp_path / "g.g2o")
    np.testing.assert_array_equal(back.measurements, graph.measurements)
    np.testing.assert_array_equal(back.information, graph.information)
    (tmp_path / "bad.g2o").write_text("VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 0 0 0\nEDGE_SE2 0 2 1 0 0 1 0 0 1 0 1\n")
    with pytest.raises(GraphError, match=r"edge 0 \(0 -> 2\) names unknown pose 2"):
        read_g2o(tmp_path / "bad.g2o")
    (tmp_path / "short.g2o").write_text("EDGE_SE2 0 1 1 0 0 1 0 0\n")
    with pytest.raises(GraphError, match="short.g2o:1: EDGE_SE2 needs 11 values, got 8"):
        read_g2o(tmp_path / "short.g2o")


def test_vertices_without_edges_and_estimates_are_written(tmp_path):
    graph = PoseGraph.from_edges([0], [1], [[1.0, 0, 0.5]], [np.eye(3)], pose_ids=[0, 1, 5])
    write_g2o(tmp_path / "g.g2o", graph, {1: np.array([1.0, 0, 0.5])})
    lines = (tmp_path / "g.g2o").read_text().splitlines()
    assert lines[:3] == ["VERTEX_SE2 0 0 0 0", "VERTEX_SE2 1 1 0 0.5", "VERTEX_SE2 5 0 0 0"]
    back = read_g2o(tmp_path / "g.g2o")
    np.testing.assert_array_equal(back.pose_ids, [0, 1, 5])
    assert back.dim == 2 and back.n_edges == 1


def test_3d_graph_is_not_written(tmp_path):
    graph = PoseGraph.from_edges([0], [1], np.zeros((1, 6)), [np.eye(6)])
    with pytest.raises(GraphError, match="g2o SE2 lines hold 2D graphs; this graph is 3D"):
        write_g2o(tmp_path / "g.g2o", graph)
