"""The pose-graph type: one validator for whole graphs and message chunks, constructors, properties."""

from __future__ import annotations

import numpy as np
import pytest

from linear_slam_ros.core.errors import GraphError
from linear_slam_ros.core.limits import InputLimits
from linear_slam_ros.pose_graph.graph import PoseGraph


@pytest.mark.parametrize(
    "over, match",
    [
        (dict(dim=4), "dimension must be 2 or 3, got 4"),
        (dict(to_ids=np.array([4])), "needs at least one edge and equal numbers"),
        (dict(measurements=np.zeros((2, 6))), "2 edges need measurements \\(2, 3\\)"),
        (dict(from_ids=np.array([-1, 3])), "pose ids must be >= 0"),
        (dict(to_ids=np.array([4, 2**62])), "pose id 4611686018427387904 is out of range \\(< 2\\*\\*53\\)"),
        (dict(to_ids=np.array([3, 7])), "edge 0 connects pose 3 to itself"),
        (dict(measurements=np.array([[np.inf, 0, 0], [0, 0, 0]])), "non-finite measurement or information"),
        (dict(information=np.stack([np.eye(3), np.triu(np.ones((3, 3)))])), "information of edge 1 \\(3->7\\) is not symmetric"),
        (dict(information=np.stack([np.eye(3), -np.eye(3)])), "information of edge 1 \\(3->7\\) is not positive definite"),
        (dict(pose_ids=[3, 4]), "edge 1 \\(3 -> 7\\) names unknown pose 7"),
    ],
)
def test_chunk_validation(over, match, make_chunk):
    with pytest.raises(GraphError, match=f"pose-graph chunk 1: {match}"):
        make_chunk(**over)


def test_empty_graph_and_the_constructor_are_validated_too(make_chunk):
    with pytest.raises(GraphError, match="^pose-graph chunk 1 has no edges$"):
        make_chunk(from_ids=[], to_ids=[], measurements=np.zeros((0, 3)), information=np.zeros((0, 3, 3)))
    good = make_chunk()
    with pytest.raises(GraphError, match="^pose graph: pose_ids must be sorted and unique$"):
        PoseGraph(2, good.from_ids, good.to_ids, good.measurements, good.information, np.array([7, 4, 3]))
    with pytest.raises(GraphError, match=r"^pose graph: edge 0 \(3 -> 4\) names unknown pose 3 \(and 1 more\)$"):
        PoseGraph(2, good.from_ids, good.to_ids, good.measurements, good.information, np.array([7]))


def test_from_edges_types_dimension_and_poses(make_chunk):
    g = make_chunk(from_ids=[3, 4], to_ids=[4, 7], pose_ids=[9, 7, 3, 4, 3], dim=None)
    assert (g.dim, g.name, g.n_edges, g.n_poses, g.is_star) == (2, "pose-graph chunk 1", 2, 4, False)
    assert g.from_ids.dtype == g.to_ids.dtype == g.pose_ids.dtype == np.int64
    np.testing.assert_array_equal(g.pose_ids, [3, 4, 7, 9])  # sorted, unique, vertex 9 without edges kept
    g3 = PoseGraph.from_edges([0, 0], [1, 2], np.zeros((2, 6)), np.stack([np.eye(6)] * 2))
    assert (g3.dim, g3.name, g3.is_star) == (3, "pose graph", True)
    np.testing.assert_array_equal(g3.pose_ids, [0, 1, 2])


def test_from_edges_keeps_float64_arrays_without_copying(make_chunk):
    chunk = make_chunk()
    again = PoseGraph.from_edges(chunk.from_ids, chunk.to_ids, chunk.measurements, chunk.information)
    assert again.measurements is chunk.measurements and again.information is chunk.information


@pytest.mark.parametrize(
    "over, match",
    [
        (dict(information=np.stack([np.eye(3), np.diag([1.0, 1.0, 1e300])])),
         "information of edge 1 \\(3->7\\): information diagonal entry 2 is 1e\\+300, above the limit max_information = 1e\\+12"),
        (dict(information=np.stack([np.diag([1e-300, 1.0, 1.0]), np.eye(3)])),
         "information of edge 0 \\(3->4\\): information diagonal entry 0 is 1e-300, below the limit min_information = 1e-12"),
        (dict(information=np.stack([np.eye(3), np.diag([1e10, 1.0, 1e-5])])),
         "information of edge 1 \\(3->7\\): information matrix is too ill-conditioned to join in double precision: "
         "condition number "
         "1e\\+15 \\(2-norm\\) is above the limit max_condition = 1e\\+14"),
        (dict(measurements=np.array([[1.0, 0, 0.1], [2.0, 1, 1e300]])),
         "measurement of edge 1 \\(3->7\\): angle 0 is 1e\\+300 rad, beyond the limit max_angle = 10000 rad"),
        (dict(measurements=np.array([[1.0, -2e6, 0.1], [2.0, 1, 0.2]])),
         "measurement of edge 0 \\(3->4\\): translation 1 is -2e\\+06 m, beyond the limit max_coordinate = 1e\\+06 m"),
    ],
)
def test_numbers_beyond_the_default_limits(over, match, make_chunk):
    with pytest.raises(GraphError, match=f"^pose-graph chunk 1: {match}$"):
        make_chunk(**over)


def test_3d_angles_and_custom_limits(make_chunk):
    z = np.zeros((2, 6))
    z[1, 4] = -2e4  # beta of edge 1
    match = "^pose graph: measurement of edge 1 \\(0->2\\): angle 1 is -2e\\+04 rad, beyond the limit max_angle"
    with pytest.raises(GraphError, match=match):
        PoseGraph.from_edges([0, 0], [1, 2], z, np.stack([np.eye(6)] * 2))
    limits = InputLimits(max_angle=4.0, min_information=0.5, max_condition=10.0)
    with pytest.raises(GraphError, match="angle 0 is 5 rad, beyond the limit max_angle = 4 rad$"):
        make_chunk(measurements=np.array([[1.0, 0, 5.0], [2.0, 1, 0.2]]), limits=limits)
    match = "edge 0 \\(3->4\\): information diagonal entry 1 is 0.1, below the limit min_information = 0.5$"
    with pytest.raises(GraphError, match=match):
        make_chunk(information=np.stack([np.diag([1.0, 0.1, 1.0]), np.eye(3)]), limits=limits)
    match = "edge 1 \\(3->7\\): .* condition number 20 \\(2-norm\\) is above the limit max_condition = 10$"
    with pytest.raises(GraphError, match=match):
        make_chunk(information=np.stack([np.eye(3), np.diag([20.0, 1.0, 1.0])]), limits=limits)
    make_chunk(measurements=np.array([[1.0, 0, 5.0], [2.0, 1, 0.2]]))  # fine by default
    good = make_chunk()
    good.validate(limits)
    with pytest.raises(GraphError, match="max_information = 1.5$"):
        good.validate(InputLimits(max_information=1.5))


def test_the_first_faulty_edge_of_a_large_graph_is_named(make_chunk):
    k = 5000
    info = np.tile(np.eye(3), (k, 1, 1))
    info[3210, 1, 1] = -1.0
    info[4000, 0, 1] = 0.5  # not symmetric, later
    with pytest.raises(GraphError, match="^pose-graph chunk 1: information of edge 3210 \\(3->3214\\) is not positive definite$"):
        make_chunk(from_ids=np.full(k, 3), to_ids=np.arange(4, k + 4), measurements=np.zeros((k, 3)), information=info)
