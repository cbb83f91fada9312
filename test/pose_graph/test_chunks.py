"""Pose graphs to local maps and back: star graphs, LAGO chunks, edge maps, graphs of datasets."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.linalg
import scipy.sparse as sp

from linear_slam_ros.core.errors import GraphError, InvalidMapError
from linear_slam_ros.core.geometry import relative_pose
from linear_slam_ros.core.limits import InputLimits
from linear_slam_ros.core.local_map import LocalMap, fuse_repeated
from linear_slam_ros.core.solvers import DENSE_MAX
from linear_slam_ros.pose_graph.chunks import (
    block_diagonal,
    chunk_end_pose,
    chunk_to_local_map,
    edge_maps,
    fuse_star_edges,
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


def test_star_map_is_checked_as_a_whole_against_the_limits(make_chunk):
    """Each edge passes the graph's per-edge checks; the map the chunk makes is refused as a whole, as
    :meth:`LocalMap.validate` would refuse it, and a valid one passes ``validate`` too."""
    information = np.stack([np.eye(3), 1e6 * np.eye(3)])  # each block condition 1, the map 1e6
    limits = InputLimits(max_condition=1e5)
    chunk = make_chunk(information=information, limits=limits)
    with pytest.raises(GraphError, match="^local map 'pose-graph chunk 1': .* condition number 1e\\+06 \\(1-norm\\) is above"):
        star_chunk_to_local_map(chunk, limits)
    local = star_chunk_to_local_map(chunk)
    local.validate()
    with pytest.raises(InvalidMapError, match="1e\\+06 \\(1-norm estimate\\) is above"):
        local.validate(limits)  # the full validation agrees
    fused = make_chunk(to_ids=np.array([4, 4]), measurements=np.array([[1.0, 0, 3.0], [1.0, 0, -3.0]]))
    match = "angle at state index 2 \\(pose 4\\) is 3.1\\d* rad, beyond the limit max_angle = 3.1 rad"
    with pytest.raises(GraphError, match=match):
        star_chunk_to_local_map(fused, InputLimits(max_angle=3.1))  # the fused angle, not a measured one, is beyond


def test_a_graph_knows_the_limits_its_numbers_passed(make_chunk):
    strict = InputLimits(max_angle=1.0)
    chunk = make_chunk()  # the default limits
    assert chunk.checked_with(None) and not chunk.checked_with(strict)
    chunk.validate(strict)
    assert chunk.checked_with(strict) and not chunk.checked_with(None)
    with pytest.raises(GraphError, match="edge 0 \\(3->4\\): angle 0 is 0.1 rad, beyond the limit max_angle = 0.05 rad"):
        chunk.validate(InputLimits(max_angle=0.05))
    assert chunk.checked_with(strict)  # a failed check does not change what passed
    assert make_chunk(limits=strict).checked_with(strict)  # from_edges' own limits


def test_a_star_map_relies_on_its_graph_checks_only_under_the_same_limits(make_chunk, monkeypatch):
    """With no edge fused and the graph checked with the same limits, only the whole matrix's
    condition is checked again; otherwise the map's bounds are checked in full."""
    full_checks: list[str] = []
    original = LocalMap.check_numbers

    def counted(self, limits=None, blocks=None):
        full_checks.append(self.name)
        return original(self, limits, blocks=blocks)

    monkeypatch.setattr(LocalMap, "check_numbers", counted)
    star_chunk_to_local_map(make_chunk())
    star_chunk_to_local_map(make_chunk(limits=InputLimits(max_angle=1.0)), InputLimits(max_angle=1.0))
    assert full_checks == []
    with pytest.raises(GraphError, match="^local map 'pose-graph chunk 1': angle at state index 2 \\(pose 4\\) is 0.1 rad"):
        star_chunk_to_local_map(make_chunk(), InputLimits(max_angle=0.05))  # checked with other limits
    assert full_checks == ["pose-graph chunk 1"]
    star_chunk_to_local_map(make_chunk(to_ids=np.array([4, 4])))  # fused: new values and blocks
    assert len(full_checks) == 2


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
            graph_from_local_maps([*edge_maps(PoseGraph.from_edges([0], [1], [[1.0, 0, 0]], [np.eye(3)])), *edges])
    back = graph_from_local_maps(edges)
    for name in ("from_ids", "to_ids", "measurements", "information", "pose_ids"):
        assert getattr(back, name).tobytes() == getattr(graph, name).tobytes(), name


def test_star_fusion_equals_fusing_the_dense_block_diagonal(rng):
    """Repeated edges fused block by block equal fuse_repeated on the dense matrix (angles wrapped next to the first)."""
    to = np.array([5, 9, 5, 6, 9, 5])
    k = to.size
    z = rng.normal(size=(k, 3))
    z[2, 2] = z[0, 2] + 2 * np.pi + 0.01  # the same heading, one turn apart
    blocks = []
    for _ in range(k):
        a = rng.normal(size=(3, 3))
        blocks.append(a @ a.T + 3 * np.eye(3))
    graph = PoseGraph.from_edges(np.full(k, 2), to, z, np.stack(blocks), name="pose-graph chunk 8")
    ids, values, info = fuse_star_edges(graph)
    dense = scipy.linalg.block_diag(*blocks)
    want_ids, _, want_x, want_info = fuse_repeated("x", 2, to, np.zeros(k, np.int8), z.ravel(), dense)
    np.testing.assert_array_equal(ids, want_ids)
    np.testing.assert_allclose(values.ravel(), want_x, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(scipy.linalg.block_diag(*info), want_info, rtol=1e-12)
    m = star_chunk_to_local_map(graph)
    np.testing.assert_array_equal(m.ids, [5, 9, 6])
    np.testing.assert_allclose(m.info_dense(), want_info, rtol=1e-12)


@pytest.mark.parametrize("dim", [2, 3])
def test_large_star_chunks_keep_a_sparse_block_diagonal(dim, rng):
    p = 3 if dim == 2 else 6
    k = DENSE_MAX // p + 1  # just above the dense threshold
    blocks = np.stack([np.eye(p) * (e + 1) + 0.1 * np.ones((p, p)) for e in range(k)])
    graph = PoseGraph.from_edges(np.zeros(k), np.arange(1, k + 1), rng.normal(size=(k, p)) * 0.1, blocks)
    m = star_chunk_to_local_map(graph)
    assert sp.issparse(m.info) and m.info.nnz == k * p * p
    np.testing.assert_array_equal(m.info_dense(), scipy.linalg.block_diag(*blocks))
    small = star_chunk_to_local_map(PoseGraph.from_edges(np.zeros(2), [1, 2], np.zeros((2, p)), blocks[:2]))
    assert isinstance(small.info, np.ndarray)
    np.testing.assert_array_equal(block_diagonal(blocks[:2]), scipy.linalg.block_diag(*blocks[:2]))


def test_lago_maps_are_checked_with_the_limits(rng, circle_graph):
    _, graph = circle_graph(rng, n=20, loops=1.0, per_loop=20)
    sel = slice(0, 8)
    chunk = PoseGraph.from_edges(
        graph.from_ids[sel], graph.to_ids[sel], graph.measurements[sel], graph.information[sel], name="pose-graph chunk 2"
    )
    assert not chunk.is_star
    local = chunk_to_local_map(chunk)
    match = "^local map 'pose-graph chunk 2 \\(LAGO\\)': coordinate at state index \\d+ \\(pose \\d+\\) is .* m, "
    with pytest.raises(GraphError, match=match + "beyond the limit max_coordinate = 0.5 m$"):
        chunk_to_local_map(chunk, InputLimits(max_coordinate=0.5))
    assert np.abs(local.x).max() > 0.5


@pytest.mark.parametrize("dim", [2, 3])
def test_edges_to_earlier_poses_are_turned_round_and_join_to_the_truth(dim, rng):
    """A g2o file whose odometry points backwards (``EDGE k+1 k``) could not be joined: the star of pose k+1 waits
    for a map that holds k+1 (review of session 26). Turned round, noise-free, it joins to the truth."""
    from linear_slam_ros.core.frames import change_frame
    from linear_slam_ros.core.geometry import wrap_angle
    from linear_slam_ros.evaluation.runner import run_join
    from linear_slam_ros.evaluation.synthetic import make_world
    from linear_slam_ros.joiner.strategy import JoinMethod
    from linear_slam_ros.pose_graph.chunks import forward_edges, star_local_maps

    world = make_world(dim, 12, 0, rng)
    pairs = [(k + 1, k) for k in range(12)] + [(10, 2), (3, 9)]
    z = np.array([relative_pose(dim, world.poses[a], world.poses[b]) for a, b in pairs])
    p = z.shape[1]
    info = np.stack([np.diag(rng.uniform(10.0, 100.0, p)) + 0.5 for _ in pairs])
    graph = PoseGraph.from_edges([a for a, _ in pairs], [b for _, b in pairs], z, info, dim=dim)
    f, t, z_fwd, info_fwd = forward_edges(graph)
    kept = {(9, 8)}  # 3 -> 9 reaches pose 9: its star joins as it is
    turned = [(a, b) if (a, b) in kept else (min(a, b), max(a, b)) for a, b in pairs]
    assert list(zip(f.tolist(), t.tolist(), strict=True)) == turned
    for e, (a, b) in enumerate(turned):
        expected = relative_pose(dim, world.poses[a], world.poses[b])
        np.testing.assert_allclose(np.r_[z_fwd[e, :dim] - expected[:dim], wrap_angle(z_fwd[e, dim:] - expected[dim:])], 0.0,
                                   atol=1e-12)
    # first order: I' = G^-T I G^-1 with G the Jacobian of the inversion (central differences here)
    e = 0
    g = np.zeros((p, p))
    for k in range(p):
        step = np.zeros(p)
        step[k] = 1e-6
        g[:, k] = (relative_pose(dim, z[e] + step, np.zeros(p)) - relative_pose(dim, z[e] - step, np.zeros(p))) / 2e-6
    g_inv = np.linalg.inv(g)
    np.testing.assert_allclose(info_fwd[e], g_inv.T @ info[e] @ g_inv, rtol=1e-7)
    # turned round twice: the edge as it was (the inversion is an involution, its Jacobians inverse to each other)
    twice = forward_edges(PoseGraph.from_edges(t[:3], f[:3], z_fwd[:3], info_fwd[:3], dim=dim))
    np.testing.assert_array_equal(twice[0], f[:3])
    np.testing.assert_allclose(twice[2], z[:3], atol=1e-12)
    np.testing.assert_allclose(twice[3], info[:3], rtol=1e-9)
    maps = star_local_maps(graph)
    assert [m.frame_id for m in maps] == sorted(set(f.tolist()))  # pose 8: no star (9 -> 8 is in star 9)
    joined = change_frame(run_join(maps, JoinMethod.DC).result, 0)
    for i, k in enumerate(joined.ids.tolist()):
        error = joined.x[joined.scalar_slice(i)] - relative_pose(dim, world.poses[0], world.poses[k])
        np.testing.assert_allclose(np.r_[error[:dim], wrap_angle(error[dim:])], 0.0, atol=1e-9)


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("method", ["dc", "online-dc"])
def test_stars_of_poses_not_numbered_one_by_one_end_at_the_next_star(dim, method, rng):
    """Poses 0, 2, 4, ... (a g2o file another tool wrote): a star's end pose was its frame's successor if held, else
    its largest id, here a loop closure's pose, and divide and conquer found no shared frame (exit code 2)."""
    from linear_slam_ros.core.frames import change_frame
    from linear_slam_ros.evaluation.runner import run_join
    from linear_slam_ros.evaluation.synthetic import make_world
    from linear_slam_ros.pose_graph.chunks import star_local_maps

    world = make_world(dim, 8, 0, rng)
    ids = 2 * np.arange(9)  # pose k of the world is pose 2k of the file
    pairs = [(k, k + 1) for k in range(8)] + [(0, 6), (2, 7)]
    z = np.array([relative_pose(dim, world.poses[a], world.poses[b]) for a, b in pairs])
    info = np.stack([np.eye(z.shape[1]) * 100.0 for _ in pairs])
    graph = PoseGraph.from_edges([ids[a] for a, _ in pairs], [ids[b] for _, b in pairs], z, info, dim=dim)
    maps = star_local_maps(graph)
    assert [m.end_id for m in maps] == [int(ids[k + 1]) for k in range(8)]  # the next star's frame, not 12 or 14
    joined = change_frame(run_join(maps, method).result, 0)
    for k in range(1, 9):  # pose 0 is the frame
        got = joined.x[joined.scalar_slice(joined.key_set[2 * int(ids[k])])]  # keys are 2 id + kind (pose 0)
        np.testing.assert_allclose(got[:dim], world.poses[k][:dim], atol=1e-9)
