"""Pose graphs to local maps and back: star graphs, LAGO chunks, edge maps, graphs of datasets."""

from __future__ import annotations

import numpy as np
import pytest

from linear_slam_ros.core.errors import GraphError
from linear_slam_ros.core.geometry import relative_pose
from linear_slam_ros.pose_graph.chunks import (
    chunk_end_pose,
    chunk_to_local_map,
    edge_maps,
    graph_from_local_maps,
    star_chunk_to_local_map,
)
from linear_slam_ros.pose_graph.graph import PoseGraph


def test_star_chunk_is_a_pose_only_local_map(make_chunk):
    m = star_chunk_to_local_map(make_chunk())
    assert m.frame_id == 3 and m.end_id == 4
    np.testing.assert_array_equal(m.ids, [4, 7])
    np.testing.assert_array_equal(m.x, [1.0, 0, 0.1, 2.0, 1, -0.2])
    np.testing.assert_array_equal(m.info_dense(), np.diag([1.0, 1, 1, 2, 2, 2]))
    assert m.name == "pose-graph chunk 1"


def test_parallel_edges_are_fused(make_chunk):
    m = chunk_to_local_map(make_chunk(to_ids=np.array([4, 4]), measurements=np.array([[1.0, 0, 0.1], [1.3, 0, 0.1]])))
    np.testing.assert_array_equal(m.ids, [4])
    np.testing.assert_allclose(m.x, [1.2, 0, 0.1])


def test_non_star_chunk_needs_lago(make_chunk):
    chunk = make_chunk(from_ids=np.array([3, 4]))
    with pytest.raises(GraphError, match="pose-graph chunk 1 is not a star"):
        star_chunk_to_local_map(chunk)


def test_chunk_through_lago_is_a_local_map_in_its_first_frame(rng, circle_graph):
    world, graph = circle_graph(rng, n=20, loops=1.0, per_loop=20)
    sel = (graph.from_ids >= 4) & (graph.to_ids <= 12)
    chunk = PoseGraph.from_edges(
        graph.from_ids[sel], graph.to_ids[sel], graph.measurements[sel], graph.information[sel], name="pose-graph chunk 3"
    )
    local = chunk_to_local_map(chunk)
    assert local.frame_id == 4 and local.end_id == 12 == chunk_end_pose(chunk.from_ids, chunk.to_ids, 4)
    assert local.name == "pose-graph chunk 3 (LAGO)"
    for i, pid in enumerate(local.ids.tolist()):
        truth = relative_pose(2, world.poses[4], world.poses[pid])
        np.testing.assert_allclose(local.x[3 * i : 3 * i + 3], truth, atol=1e-9)
    chunk3d = PoseGraph.from_edges([0, 1], [1, 2], np.zeros((2, 6)), np.stack([np.eye(6)] * 2), name="pose-graph chunk 1")
    with pytest.raises(GraphError, match="LAGO is 2D only"):
        chunk_to_local_map(chunk3d)


def test_chunk_end_pose_follows_the_odometry_chain():
    assert chunk_end_pose(np.array([4, 6, 5]), np.array([5, 5, 9]), 4) == 6  # either direction counts
    assert chunk_end_pose(np.array([4]), np.array([6]), 4) == 4


@pytest.mark.parametrize("dim", [2, 3])
def test_edge_maps_and_graph_from_local_maps_are_inverse(dim, rng, circle_graph):
    if dim == 2:
        _, graph = circle_graph(rng, n=12, loops=1.0, per_loop=6)
    else:
        info = np.stack([np.eye(6) * (k + 1) for k in range(3)])
        graph = PoseGraph.from_edges([0, 1, 0], [1, 2, 2], rng.normal(size=(3, 6)), info)
    edges = edge_maps(graph)
    assert [(m.dim, m.frame_id, m.end_id, m.ids.tolist(), m.name) for m in edges[:2]] == [
        (dim, int(graph.from_ids[e]), int(graph.to_ids[e]), [int(graph.to_ids[e])], f"edge_{e}") for e in range(2)
    ]
    if dim == 3:
        with pytest.raises(GraphError, match="map 'edge_0' is not a 2D pose-only map"):
            graph_from_local_maps(edges)
        return
    back = graph_from_local_maps(edges)
    for name in ("from_ids", "to_ids", "measurements", "information", "pose_ids"):
        assert getattr(back, name).tobytes() == getattr(graph, name).tobytes(), name
