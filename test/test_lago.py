"""LAGO: exact on noise-free graphs, regularisation of orientations, errors, g2o, golden figures."""

from __future__ import annotations

import numpy as np
import pytest

from linear_slam_ros.core.errors import GraphError
from linear_slam_ros.core.geometry import relative_pose, wrap_angle
from linear_slam_ros.pose_graph.lago import (
    PoseGraph,
    chunk_end_pose,
    edge_maps,
    graph_from_local_maps,
    lago,
    read_g2o,
    write_g2o,
)
from linear_slam_ros.evaluation.nonlinear import gauss_newton
from linear_slam_ros.evaluation.objective import MapObjective
from linear_slam_ros.pose_graph.chunks import PoseGraphChunk, chunk_to_local_map
from linear_slam_ros.evaluation.synthetic import make_world


def circle_graph(rng, n=60, loops=3.0, per_loop=20, sigma=(0.0, 0.0)):
    """A robot driving ``loops`` circles: odometry edges and a loop closure to the same spot one lap earlier."""
    world = make_world(2, n, 0, rng, loops=loops)
    pairs = [(k, k + 1) for k in range(n)] + [(k, k + per_loop) for k in range(0, n - per_loop + 1, 2)]
    f, t, z, info = [], [], [], []
    for a, b in pairs:
        rel = relative_pose(2, world.poses[a], world.poses[b])
        noise = rng.normal(size=3) * np.array([sigma[0], sigma[0], sigma[1]])
        z.append(np.r_[rel[:2] + noise[:2], wrap_angle(rel[2] + noise[2])])
        f.append(a), t.append(b)
        s = np.array([max(sigma[0], 1e-3)] * 2 + [max(sigma[1], 1e-3)])
        info.append(np.diag(s**-2))
    return world, PoseGraph.from_edges(f, t, np.array(z), np.array(info))


def _error(result, world):
    x = result.map.x.reshape(-1, 3)
    truth = world.poses[result.map.ids]
    return max(np.abs(x[:, :2] - truth[:, :2]).max(), np.abs(wrap_angle(x[:, 2] - truth[:, 2])).max())


def test_noise_free_graph_gives_the_truth(rng):
    world, graph = circle_graph(rng)
    assert _error(lago(graph, 0), world) < 1e-9


def test_regularisation_is_what_makes_loops_work(rng):
    world, graph = circle_graph(rng, sigma=(0.01, 0.002))
    good = lago(graph, 0)
    assert np.count_nonzero(good.chord_corrections) > 0  # laps add 2 pi to loop closures
    bad = lago(graph, 0, regularization=False)
    edges = edge_maps(graph)
    optimum = gauss_newton(good.map, edges)
    err_good = np.abs(good.map.x - optimum.map.x).max()
    err_bad = np.abs(bad.map.x - optimum.map.x).max()
    assert err_good < 0.05  # within the noise level of the optimum
    assert err_bad > 1.0  # metres off without regularisation
    chi2 = MapObjective.build(good.map, edges).chi2
    assert chi2(good.map.x) < 1.05 * optimum.chi2
    assert chi2(bad.map.x) > 100 * optimum.chi2


def test_disconnected_graph_and_unknown_poses_are_rejected():
    z = np.zeros((2, 3))
    info = np.stack([np.eye(3)] * 2)
    with pytest.raises(GraphError, match="pose graph is disconnected: 2 components; pose 5 is not connected to anchor pose 0"):
        lago(PoseGraph.from_edges([0, 5], [1, 6], z + [1, 0, 0], info))
    with pytest.raises(GraphError, match=r"edge 1 \(1 -> 9\) names unknown pose 9"):
        PoseGraph.from_edges([0, 1], [1, 9], z, info, pose_ids=[0, 1, 2])
    with pytest.raises(GraphError, match="anchor pose 7 is not in the pose graph"):
        lago(PoseGraph.from_edges([0, 1], [1, 2], z, info), anchor_id=7)
    with pytest.raises(GraphError, match="edge 0 connects pose 1 to itself"):
        PoseGraph.from_edges([1, 1], [1, 2], z, info)
    with pytest.raises(GraphError, match="pose graph has no edges"):
        PoseGraph.from_edges([], [], np.zeros((0, 3)), np.zeros((0, 3, 3)))


def test_g2o_round_trip_and_errors(tmp_path, rng):
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


def test_coupled_information_uses_the_block_diagonal_approximation(rng):
    _, graph = circle_graph(rng, sigma=(0.01, 0.002))
    info = graph.information.copy()
    info[:, 0, 2] = info[:, 2, 0] = 0.1 * np.sqrt(info[:, 0, 0] * info[:, 2, 2])
    coupled = PoseGraph.from_edges(graph.from_ids, graph.to_ids, graph.measurements, info)
    assert lago(coupled, 0).n_coupled_edges == graph.n_edges


def test_chunk_through_lago_is_a_local_map_in_its_first_frame(rng):
    world, graph = circle_graph(rng, n=20, loops=1.0, per_loop=20)
    sel = (graph.from_ids >= 4) & (graph.to_ids <= 12)
    chunk = PoseGraphChunk(2, 3, graph.from_ids[sel], graph.to_ids[sel], graph.measurements[sel], graph.information[sel])
    local = chunk_to_local_map(chunk)
    assert local.frame_id == 4 and local.end_id == 12 == chunk_end_pose(chunk.from_ids, chunk.to_ids, 4)
    for i, pid in enumerate(local.ids.tolist()):
        truth = relative_pose(2, world.poses[4], world.poses[pid])
        np.testing.assert_allclose(local.x[3 * i : 3 * i + 3], truth, atol=1e-9)
    chunk3d = PoseGraphChunk(3, 1, np.array([0, 1]), np.array([1, 2]), np.zeros((2, 6)), np.stack([np.eye(6)] * 2))
    with pytest.raises(GraphError, match="LAGO is 2D only"):
        chunk_to_local_map(chunk3d)


def test_intel_lago_is_close_to_the_optimum(read_benchmark):
    graph = graph_from_local_maps(list(read_benchmark("Intel").maps))
    result = lago(graph, 0)
    edges = edge_maps(graph)
    chi2 = MapObjective.build(result.map, edges).chi2(result.map.x)
    assert chi2 == pytest.approx(546.46, rel=0.001)  # the paper's Nonlinear LS optimum
