"""Joining maps without a common frame pose: feature-defined frames (App. B) and island links."""

from __future__ import annotations

import numpy as np
import pytest

from linear_slam_ros.core.errors import FrameError
from linear_slam_ros.core.frames import change_frame
from linear_slam_ros.core.geometry import wrap_angle
from linear_slam_ros.core.local_map import FEATURE, POSE, LocalMap, to_dense
from linear_slam_ros.evaluation.synthetic import exact_local_maps, exact_map, make_world
from linear_slam_ros.joining.divide_conquer import join_divide_and_conquer
from linear_slam_ros.joining.feature_frame import (
    from_feature_frame,
    join_feature_framed,
    to_feature_frame,
)
from linear_slam_ros.joining.islands import Link, find_link, maps_within, merge_maps, poses_of
from linear_slam_ros.joining.pairwise import join_pair


def _random_map(dim: int, rng: np.random.Generator) -> LocalMap:
    p = 3 if dim == 2 else 6
    kinds = np.array([POSE, POSE, POSE, FEATURE, FEATURE, FEATURE, FEATURE], dtype=np.int8)
    ids = np.array([1, 2, 3, 10, 11, 12, 13])
    parts = [np.r_[rng.normal(size=dim) * 5, rng.uniform(-1, 1, p - dim)] if k == POSE else rng.normal(size=dim) * 5
             for k in kinds]
    x = np.concatenate(parts)
    a = rng.normal(size=(x.size, x.size))
    return LocalMap(dim, 0, 3, ids, kinds, x, a @ a.T + x.size * np.eye(x.size), "random")


def _by_key(m: LocalMap) -> tuple[np.ndarray, np.ndarray]:
    """State and information in the order of sorted keys (to compare maps whose variables are ordered differently)."""
    order = np.argsort(m.keys)
    idx = m.scalar_index(order)
    return m.x[idx], to_dense(m.info)[np.ix_(idx, idx)]


@pytest.mark.parametrize("dim", [2, 3])
def test_feature_frame_round_trip_is_exact(dim):
    m = _random_map(dim, np.random.default_rng(dim))
    frame = (10, 11) if dim == 2 else (10, 11, 12)
    framed = to_feature_frame(m, frame)
    assert framed.ids.tolist()[-1] == 0 and framed.kinds[-1] == POSE  # the old frame pose is a variable now
    assert framed.x.size == m.x.size  # same number of scalars: the frame features lose what the frame pose brings
    back = from_feature_frame(framed, 0, 3, "back")
    x_back, info_back = _by_key(back)
    x, info = _by_key(m)
    np.testing.assert_allclose(x_back, x, atol=1e-12)
    np.testing.assert_allclose(info_back, info, rtol=1e-11, atol=1e-11 * np.abs(info).max())


@pytest.mark.parametrize("dim", [2, 3])
def test_feature_frame_information_is_the_linearised_transform(dim):
    """I_y = J^-T I_x J^-1 with J the numerical derivative of the state's change (no shared code with the module)."""
    m = _random_map(dim, np.random.default_rng(10 + dim))
    frame = (10, 11) if dim == 2 else (10, 11, 12)
    framed = to_feature_frame(m, frame)
    h = 1e-6
    jac = np.empty((m.x.size, m.x.size))
    for j in range(m.x.size):
        plus, minus = m.x.copy(), m.x.copy()
        plus[j] += h
        minus[j] -= h
        yp = to_feature_frame(m.replace(x=plus), frame).x
        ym = to_feature_frame(m.replace(x=minus), frame).x
        jac[:, j] = (yp - ym) / (2 * h)
    inv = np.linalg.inv(jac)
    expected = inv.T @ to_dense(m.info) @ inv
    np.testing.assert_allclose(to_dense(framed.info), expected, rtol=1e-6, atol=1e-6 * np.abs(expected).max())


def test_feature_frame_errors_name_the_problem():
    m = _random_map(2, np.random.default_rng(0))
    with pytest.raises(FrameError, match="frame feature 99 is not in map 'random'"):
        to_feature_frame(m, (10, 99))
    framed = to_feature_frame(m, (10, 11))
    with pytest.raises(FrameError, match="cannot move a feature-framed map to the frame of pose 42: not in the map"):
        from_feature_frame(framed, 42, 42, "x")
    other = to_feature_frame(m, (11, 12))
    with pytest.raises(FrameError, match=r"frame of features \(10, 11\) with a 2D map in the frame of features \(11, 12\)"):
        join_feature_framed(framed, other)


def _two_halves(dim: int) -> tuple[list[LocalMap], LocalMap, LocalMap]:
    """Noise-free pose-feature maps of one world, split into two halves that share features but no pose."""
    world = make_world(dim, 24, 40, np.random.default_rng(3))
    maps = exact_local_maps(world, np.random.default_rng(4), poses_per_map=2, sensor_range=8.0)
    first = join_divide_and_conquer(maps[:5])
    second = join_divide_and_conquer(maps[6:])  # map 6 lost: the halves share no pose
    return maps, first, second


@pytest.mark.parametrize("dim", [2, 3])
def test_islands_sharing_only_features_join_exactly_on_noise_free_maps(dim):
    """Lemma 1's setting: consistent maps join to the truth whatever their information, through a feature frame."""
    maps, first, second = _two_halves(dim)
    link = find_link(first, second)
    assert link is not None and link.pose_id is None and len(link.feature_ids) == dim
    joined = merge_maps(first, second, link, second.end_id)
    truth = join_divide_and_conquer(maps)  # exact too: every map is the truth in its frame
    assert joined.frame_id == truth.frame_id == second.end_id
    held = set(first.keys.tolist()) | set(second.keys.tolist()) | {2 * first.frame_id, 2 * second.frame_id}
    assert set(joined.keys.tolist()) == held - {2 * joined.frame_id}
    assert set(joined.keys.tolist()) <= set(truth.keys.tolist())  # all but the lost map's own poses
    idx_j = joined.scalar_index([joined.index_of(int(k)) for k in joined.keys])
    idx_t = truth.scalar_index([truth.index_of(int(k)) for k in joined.keys])
    diff = joined.x[idx_j] - truth.x[idx_t]
    diff[joined.angles[idx_j]] = wrap_angle(diff[joined.angles[idx_j]])
    np.testing.assert_allclose(diff, 0.0, atol=1e-9)
    assert np.allclose(to_dense(joined.info), to_dense(joined.info).T)
    assert np.linalg.eigvalsh(to_dense(joined.info)).min() > 0


def test_a_common_pose_joins_as_the_pairwise_join_does():
    world = make_world(2, 12, 20, np.random.default_rng(7))
    maps = exact_local_maps(world, np.random.default_rng(8), poses_per_map=3)
    link = find_link(maps[0], maps[1])
    assert link == Link(maps[1].frame_id, (), link.n_common) and link.n_common >= 1
    merged = merge_maps(maps[0], maps[1], link, maps[1].end_id)
    paired = join_pair(maps[0], maps[1])
    x_m, info_m = _by_key(merged)
    x_p, info_p = _by_key(paired)
    np.testing.assert_allclose(x_m, x_p, atol=1e-12)
    np.testing.assert_allclose(info_m, info_p, rtol=1e-9, atol=1e-9 * np.abs(info_p).max())


def test_find_link_needs_enough_well_placed_features():
    world = make_world(3, 10, 30, np.random.default_rng(9))
    rng = np.random.default_rng(10)
    a = exact_map(world, 0, [1, 2], [1, 2, 3, 4], rng, 2, "a")
    b2 = exact_map(world, 8, [9], [1, 2, 20], rng, 9, "b2")  # 2 common features: a 3D frame needs 3
    assert find_link(a, b2) is None
    b3 = exact_map(world, 8, [9], [1, 2, 3, 20], rng, 9, "b3")
    link = find_link(a, b3)
    assert link is not None and sorted(link.feature_ids) == [1, 2, 3]
    line = {1: np.zeros(3), 2: np.array([1.0, 0, 0]), 3: np.array([2.0, 0, 0])}  # collinear frame features
    world.features.update(line)
    assert find_link(exact_map(world, 0, [1], [1, 2, 3], rng, 1, "c"), exact_map(world, 8, [9], [1, 2, 3], rng, 9, "d")) is None
    flat = make_world(2, 10, 5, np.random.default_rng(1))
    assert find_link(a, exact_map(flat, 0, [1], [1, 2], rng, 1, "2d")) is None  # other dimension
    pose = exact_map(world, 2, [5], [], rng, 5, "pose")  # in the frame of a's pose 2: a common pose
    assert find_link(a, pose) == Link(2, (), 1)
    assert poses_of(a).tolist() == [0, 1, 2]


def test_merge_maps_errors_name_the_poses():
    maps, first, second = _two_halves(2)
    link = find_link(first, second)
    assert link is not None
    with pytest.raises(FrameError, match="pose 999 .* is in neither"):
        merge_maps(first, second, link, 999)
    shared = find_link(maps[0], maps[1])
    assert shared is not None
    with pytest.raises(FrameError, match="999"):
        merge_maps(maps[0], maps[1], shared, 999)


def test_maps_within_lists_an_islands_own_submaps():
    maps, first, _ = _two_halves(2)
    assert [m.name for m in maps_within(first, maps)] == [m.name for m in maps[:5]]
    assert maps_within(change_frame(first, 3), maps[:2]) == maps[:2]
