"""Divide and conquer level by level (joining/batched.py) against the pair-by-pair tree it replaces."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp

from linear_slam_ros.core.errors import FrameError, InvalidMapError
from linear_slam_ros.core.frames import change_frame
from linear_slam_ros.core.geometry import wrap_angle
from linear_slam_ros.core.local_map import POSE, LocalMap, to_dense
from linear_slam_ros.evaluation.city import city2d, garage3d
from linear_slam_ros.evaluation.objective import chi2
from linear_slam_ros.evaluation.synthetic import exact_local_maps, exact_pose_graph_maps, make_world, noisy_local_maps
from linear_slam_ros.joining.batched import MapBatch, change_frames, divide_and_conquer_levels, join_pairs
from linear_slam_ros.joining.divide_conquer import divide_and_conquer, join_divide_and_conquer
from linear_slam_ros.joining.pairwise import join_at_seam


def _pairwise(maps: list[LocalMap]) -> LocalMap:
    return divide_and_conquer(maps, join_at_seam)


def _assert_same_map(got: LocalMap, want: LocalMap, atol: float) -> None:
    assert (got.frame_id, got.end_id) == (want.frame_id, want.end_id)
    assert got.keys.tolist() == want.keys.tolist()  # the same variables in the same order
    diff = got.x - want.x
    diff[want.angles] = wrap_angle(diff[want.angles])  # an angle at pi may come out as -pi
    np.testing.assert_allclose(diff, 0.0, rtol=0, atol=atol)
    info_want = to_dense(want.info)
    np.testing.assert_allclose(to_dense(got.info), info_want, rtol=0, atol=atol * np.abs(info_want).max())


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("n_maps", [2, 3, 7, 16, 21])  # odd counts: a map moves up a level unchanged
def test_levels_equal_the_pairwise_tree_on_noisy_pose_feature_maps(dim, n_maps, rng):
    world = make_world(dim, 2 * n_maps, 3 * n_maps, rng, loops=1.3)
    maps = noisy_local_maps(world, rng, steps_per_map=2)
    assert len(maps) == n_maps
    _assert_same_map(divide_and_conquer_levels(maps), _pairwise(maps), 1e-10)


@pytest.mark.parametrize("dim", [2, 3])
def test_levels_equal_the_pairwise_tree_on_pose_graphs_with_forward_loop_closures(dim, rng):
    world = make_world(dim, 45, 0, rng, loops=1.5)  # orientations wrap past pi
    maps = exact_pose_graph_maps(world, rng, loop_every=4, loop_span=9)
    noisy = [m.replace(x=m.x + 1e-3 * rng.standard_normal(m.x.size)) for m in maps]
    _assert_same_map(divide_and_conquer_levels(noisy), _pairwise(noisy), 1e-10)


@pytest.mark.parametrize("stream", [lambda: city2d(600, seed=3), lambda: garage3d(300, seed=3)])
def test_levels_equal_the_pairwise_tree_on_the_synthetic_city_and_garage(stream):
    maps = list(stream().maps)
    got, want = join_divide_and_conquer(maps), _pairwise(maps)
    if want.end_id != want.frame_id:
        want = change_frame(want, want.end_id)
    _assert_same_map(got, want, 1e-8)
    assert chi2(got, maps) == pytest.approx(chi2(want, maps), rel=1e-10)


def test_maps_without_an_end_pose_are_aligned_as_the_pairwise_join_does(rng):
    world = make_world(2, 12, 20, rng)
    maps = [m.replace(end_id=None) for m in exact_local_maps(world, rng, poses_per_map=3)]
    _assert_same_map(divide_and_conquer_levels(maps[:3]), _pairwise(maps[:3]), 1e-10)
    # four: the two halves, each in its first map's frame, share no pose; both trees say so alike
    with pytest.raises(FrameError) as pairwise_error:
        _pairwise(maps)
    with pytest.raises(FrameError, match="is in the frame of pose 9, which is not in map 'global'") as levels_error:
        divide_and_conquer_levels(maps)
    assert str(levels_error.value) == str(pairwise_error.value)
    # the earlier map in the frame of the later one's pose: the earlier one moves
    a, b = exact_local_maps(world, rng, poses_per_map=3)[:2]
    a_later_frame = change_frame(a, a.pose_ids[-1]).replace(end_id=None)
    b_first = change_frame(b, b.pose_ids[0]).replace(end_id=None)
    _assert_same_map(divide_and_conquer_levels([b_first, a_later_frame]), _pairwise([b_first, a_later_frame]), 1e-10)


@pytest.mark.parametrize("dim", [2, 3])
def test_change_frames_moves_every_map_as_change_frame_does(dim, rng):
    world = make_world(dim, 12, 15, rng, loops=1.2)
    maps = noisy_local_maps(world, rng, steps_per_map=3)
    batch = MapBatch.of_maps(maps)
    movers = np.array([0, 2, 3], dtype=np.int64)
    targets = [int(maps[j].pose_ids[-1]) for j in movers]
    slots = batch.find(movers, 2 * np.array(targets) + POSE)
    moved = change_frames(change_frames(batch, movers[:1], slots[:1]), movers[1:], slots[1:])  # composed
    for j, m in enumerate(maps):
        want = change_frame(m, targets[list(movers).index(j)]) if j in movers else m
        _assert_same_map(moved.map_at(j, m.name), want, 1e-11)


def test_sparse_information_and_the_level_callback(rng):
    """Maps whose information is CSR (the pose-graph datasets' joined maps) take the sparse path of the batch."""
    world = make_world(3, 24, 20, rng, loops=1.2)
    maps = noisy_local_maps(world, rng, steps_per_map=2)
    mixed = [m.replace(info=sp.csr_matrix(m.info)) if i % 3 else m for i, m in enumerate(maps)]
    levels: list[tuple[float, int]] = []
    got = divide_and_conquer_levels(mixed, lambda seconds, joins: levels.append((seconds, joins)))
    _assert_same_map(got, _pairwise(maps), 1e-10)
    assert [joins for _, joins in levels] == [6, 3, 1, 1] and all(seconds >= 0 for seconds, _ in levels)  # 12 maps


def test_find_returns_minus_one_for_absent_keys(rng):
    maps = exact_local_maps(make_world(2, 6, 4, rng), rng, poses_per_map=2)
    batch = MapBatch.of_maps(maps)
    held = int(maps[1].keys[0])
    np.testing.assert_array_equal(batch.find(np.array([1, 0, 1]), np.array([held, 10**9, -5])), [maps[0].n_vars, -1, -1])
    empty = maps[0].replace(ids=maps[0].ids[:0], kinds=maps[0].kinds[:0], x=maps[0].x[:0], info=np.zeros((0, 0)))
    nothing = MapBatch.of_maps([empty, empty])
    np.testing.assert_array_equal(nothing.find(np.array([0, 1]), np.array([held, 3])), [-1, -1])


def test_errors_name_the_maps_and_poses(rng):
    maps = exact_local_maps(make_world(2, 12, 10, rng), rng, poses_per_map=2)
    with pytest.raises(InvalidMapError, match="no local maps to join"):
        divide_and_conquer_levels([])
    assert divide_and_conquer_levels(maps[:1]) is maps[0]
    m3 = exact_local_maps(make_world(3, 6, 5, rng), rng, 2)
    with pytest.raises(InvalidMapError, match="cannot join a 2D map 'exact_1' with a 3D map 'exact_1'"):
        divide_and_conquer_levels([maps[0], m3[0]])
    # neighbours with no pose in common: map 3 does not hold map 1's end pose
    with pytest.raises(FrameError, match=r"map 'exact_3' \(frame pose 4\) does not hold pose 2, the end pose of map "
                                         r"'exact_1' \(frame pose 0\): the maps share no frame"):
        divide_and_conquer_levels([maps[0], maps[2]])
    no_end = [maps[0].replace(end_id=None), maps[2].replace(end_id=None)]
    with pytest.raises(FrameError, match="is in the frame of pose 4, which is not in map 'exact_1'"):
        divide_and_conquer_levels(no_end)
    # the seam is the earlier map's end pose, but that map does not hold it
    stray = maps[0].replace(end_id=99)
    with pytest.raises(FrameError, match="does not hold pose 99, the end pose of map 'exact_1'"):
        divide_and_conquer_levels([stray, maps[1]])
    holds = maps[1].replace(ids=np.where(maps[1].ids == 4, 99, maps[1].ids), end_id=99)
    with pytest.raises(FrameError, match=r"cannot change map 'exact_1' \(frame pose 0\) to the frame of pose 99"):
        divide_and_conquer_levels([stray, holds.replace(frame_id=2)])
    with pytest.raises(InvalidMapError, match="are in frames 0 and 2; align them first"):
        join_pairs(MapBatch.of_maps(maps[:2]))


@pytest.mark.parametrize("method", ["dc", "online-dc"])
def test_a_long_noise_free_chain_is_joined_exactly(method):
    """Lemma 1: noise-free submaps are joined exactly, however long the chain. The joins solved for absolute
    coordinates, so round-off grew with the chain's lever arms: this 1.6 km chain with loop closures ended 4.4e-5 m off
    (dc) and 3.3e-6 m (online-dc). They now solve for the correction to a start point."""
    from linear_slam_ros.evaluation.runner import run_join
    from linear_slam_ros.evaluation.synthetic import World

    n = 1600
    poses = np.zeros((n + 1, 3))
    poses[:, 0] = np.arange(n + 1.0)  # 1 m a step, bending slowly away from the x axis
    poses[:, 1] = 1e-4 * np.arange(n + 1.0) ** 1.5
    maps = exact_pose_graph_maps(World(2, poses, {}), np.random.default_rng(1), loop_every=7, loop_span=5)
    joined = change_frame(run_join(maps, method).result, 0)
    x = np.stack([joined.x[joined.scalar_slice(i)] for i in range(joined.n_vars)])
    np.testing.assert_allclose(x[:, :2], poses[joined.ids, :2], rtol=0, atol=1e-9)
