"""LAGO: exact on noise-free graphs, regularisation of orientations, errors, golden figures."""

from __future__ import annotations

import numpy as np
import pytest

from linear_slam_ros.core.errors import GraphError
from linear_slam_ros.core.geometry import wrap_angle
from linear_slam_ros.evaluation.nonlinear import gauss_newton
from linear_slam_ros.evaluation.objective import MapObjective
from linear_slam_ros.pose_graph.chunks import edge_maps, graph_from_local_maps
from linear_slam_ros.pose_graph.graph import PoseGraph
from linear_slam_ros.pose_graph.lago import lago


def _error(result, world):
    x = result.map.x.reshape(-1, 3)
    truth = world.poses[result.map.ids]
    return max(np.abs(x[:, :2] - truth[:, :2]).max(), np.abs(wrap_angle(x[:, 2] - truth[:, 2])).max())


def test_noise_free_graph_gives_the_truth(rng, circle_graph):
    world, graph = circle_graph(rng)
    assert _error(lago(graph, 0), world) < 1e-9


def test_regularisation_is_what_makes_loops_work(rng, circle_graph):
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


def test_3d_graph_is_rejected():
    graph = PoseGraph.from_edges([0, 1], [1, 2], np.zeros((2, 6)), np.stack([np.eye(6)] * 2))
    with pytest.raises(GraphError, match="^pose graph: LAGO is 2D only; this graph is 3D$"):
        lago(graph)


def test_coupled_information_uses_the_block_diagonal_approximation(rng, circle_graph):
    _, graph = circle_graph(rng, sigma=(0.01, 0.002))
    info = graph.information.copy()
    info[:, 0, 2] = info[:, 2, 0] = 0.1 * np.sqrt(info[:, 0, 0] * info[:, 2, 2])
    coupled = PoseGraph.from_edges(graph.from_ids, graph.to_ids, graph.measurements, info)
    assert lago(coupled, 0).n_coupled_edges == graph.n_edges


def test_intel_lago_is_close_to_the_optimum(read_benchmark):
    graph = graph_from_local_maps(list(read_benchmark("Intel").maps))
    result = lago(graph, 0)
    edges = edge_maps(graph)
    chi2 = MapObjective.build(result.map, edges).chi2(result.map.x)
    assert chi2 == pytest.approx(546.46, rel=0.001)  # the paper's Nonlinear LS optimum
