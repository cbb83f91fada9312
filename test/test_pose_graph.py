"""Pose-graph chunks: validation and the star-chunk local map."""

from __future__ import annotations

import numpy as np
import pytest

from linear_slam_ros.core.errors import GraphError
from linear_slam_ros.pose_graph.chunks import PoseGraphChunk, chunk_to_local_map, star_chunk_to_local_map


def _chunk(**over):
    kw = dict(
        dim=2,
        seq=1,
        from_ids=np.array([3, 3]),
        to_ids=np.array([4, 7]),
        measurements=np.array([[1.0, 0, 0.1], [2.0, 1, -0.2]]),
        information=np.stack([np.eye(3), 2 * np.eye(3)]),
    )
    kw.update(over)
    return PoseGraphChunk(**kw)


def test_star_chunk_is_a_pose_only_local_map():
    m = star_chunk_to_local_map(_chunk())
    assert m.frame_id == 3 and m.end_id == 4
    np.testing.assert_array_equal(m.ids, [4, 7])
    np.testing.assert_array_equal(m.x, [1.0, 0, 0.1, 2.0, 1, -0.2])
    np.testing.assert_array_equal(m.info_dense(), np.diag([1.0, 1, 1, 2, 2, 2]))


def test_parallel_edges_are_fused():
    m = chunk_to_local_map(_chunk(to_ids=np.array([4, 4]), measurements=np.array([[1.0, 0, 0.1], [1.3, 0, 0.1]])))
    np.testing.assert_array_equal(m.ids, [4])
    np.testing.assert_allclose(m.x, [1.2, 0, 0.1])


@pytest.mark.parametrize(
    "over, match",
    [
        (dict(dim=4), "dimension must be 2 or 3, got 4"),
        (dict(to_ids=np.array([4])), "needs at least one edge and equal numbers"),
        (dict(measurements=np.zeros((2, 6))), "2 edges need measurements \\(2, 3\\)"),
        (dict(from_ids=np.array([-1, 3])), "pose ids must be >= 0"),
        (dict(to_ids=np.array([3, 7])), "edge 0 connects pose 3 to itself"),
        (dict(measurements=np.array([[np.inf, 0, 0], [0, 0, 0]])), "non-finite measurement or information"),
        (dict(information=np.stack([np.eye(3), np.triu(np.ones((3, 3)))])), "information of edge 1 \\(3->7\\) is not symmetric"),
        (dict(information=np.stack([np.eye(3), -np.eye(3)])), "information of edge 1 \\(3->7\\) is not positive definite"),
    ],
)
def test_chunk_validation(over, match):
    with pytest.raises(GraphError, match=f"pose-graph chunk 1: {match}"):
        _chunk(**over)


def test_non_star_chunk_needs_lago():
    chunk = _chunk(from_ids=np.array([3, 4]))
    with pytest.raises(GraphError, match="pose-graph chunk 1 is not a star"):
        star_chunk_to_local_map(chunk)
