"""Feature-only joining as submaps arrive (map_type feature-only): equals the batch pipeline."""

from __future__ import annotations

import numpy as np
import pytest

from linear_slam_ros.core.errors import InvalidMapError
from linear_slam_ros.core.local_map import FEATURE, POSE, LocalMap
from linear_slam_ros.evaluation.synthetic import exact_pose_graph_maps, make_world, noisy_local_maps
from linear_slam_ros.feature_only.conversion import to_feature_only
from linear_slam_ros.feature_only.joining import join_feature_maps, join_features_dc, join_features_sequential
from linear_slam_ros.feature_only.online import FeatureJoinState, feature_result, feature_step
from linear_slam_ros.feature_only.precondition import precondition
from linear_slam_ros.joiner.joiner import Joiner
from linear_slam_ros.joiner.registry import get_strategy
from linear_slam_ros.joiner.strategy import JoinMethod, MapType
from linear_slam_ros.joining.divide_conquer import counter_push, merge_stack
from support import global_feature_map_of, global_map_of


def _maps(dim: int, n_poses: int = 24, seed: int = 31, steps: int = 3, sensor_range: float = 7.0):
    world = make_world(dim, n_poses, 30, np.random.default_rng(seed))
    return noisy_local_maps(world, np.random.default_rng(seed + 1), steps_per_map=steps, sensor_range=sensor_range)


def _run(maps, method):
    strategy = get_strategy(method, MapType.FEATURE_ONLY)
    state = strategy.empty()
    for m in maps:
        state = strategy.step(state, m)
    return state


@pytest.mark.parametrize("dim", [2, 3])
def test_online_sequential_equals_the_batch_pipeline(dim):
    maps = _maps(dim, steps=1, sensor_range=4.0)
    groups = precondition(maps)
    assert 2 < len(groups) < len(maps)  # some submaps were merged, some groups closed
    batch = join_features_sequential([to_feature_only(g) for g in groups])
    online = feature_result(_run(maps, JoinMethod.SEQUENTIAL))
    assert online.frame_ids == batch.frame_ids
    np.testing.assert_array_equal(online.ids, batch.ids)
    np.testing.assert_allclose(online.x, batch.x, rtol=0, atol=1e-12)


def test_online_dc_equals_batch_dc_on_a_power_of_two():
    maps = _maps(2, n_poses=60, steps=2)
    groups = precondition(maps)
    n = 1 << (len(groups).bit_length() - 1)
    # the maps that make up the first n groups: stop before the map that closes group n + 1
    closing = [m for m in maps if any(g.frame_id == m.frame_id for g in groups)]
    prefix = maps[: maps.index(closing[n])] if n < len(groups) else maps
    batch = join_features_dc([to_feature_only(g) for g in groups[:n]])
    online = feature_result(_run(prefix, JoinMethod.ONLINE_DC))
    assert online.frame_ids == batch.frame_ids
    np.testing.assert_allclose(online.x, batch.x, rtol=0, atol=1e-12)


def test_the_open_group_waits_for_a_feature_frame():
    maps = _maps(2)
    one_feature = maps[0].replace(
        ids=maps[0].ids[:2], kinds=maps[0].kinds[:2],
        x=maps[0].x[: maps[0].offsets[2]],
        info=maps[0].info_dense()[: maps[0].offsets[2], : maps[0].offsets[2]] + 0.0,
    )
    assert (one_feature.kinds == POSE).sum() == 1 and (one_feature.kinds == FEATURE).sum() == 1
    state = feature_step(FeatureJoinState(), one_feature, divide_and_conquer=False)
    assert feature_result(state) is None  # one feature defines no frame yet


def _two_feature_map(frame: int, f10: list[float], f11: list[float]) -> LocalMap:
    """A 2D map from pose ``frame`` to ``frame + 1`` (1 m ahead) seeing features 10 and 11."""
    x = np.r_[1.0, 0.0, 0.0, f10, f11]
    return LocalMap(2, frame, frame + 1, np.array([frame + 1, 10, 11]), np.array([POSE, FEATURE, FEATURE]), x,
                    np.diag([100.0, 100, 100, 10, 10, 10, 10]), name=f"local map {frame + 1}")


@pytest.mark.parametrize("method", [JoinMethod.SEQUENTIAL, JoinMethod.ONLINE_DC])
def test_a_submap_whose_features_coincide_is_merged_with_the_next_and_never_blocks_the_map(method):
    """Alone, submap 3 (features 10 and 11 5e-8 m apart) defines no frame: the group it starts is merged with
    submap 4 instead of closed (closed, it could not be converted, and each later submap failed closing it)."""
    maps = []
    for s in range(1, 9):
        c = [9.0 - s, 2.0]
        maps.append(_two_feature_map(s - 1, c, [c[0] + 5e-8, 2.0] if s == 3 else [c[0], 5.0]))
    j = Joiner(method, MapType.FEATURE_ONLY)
    assert [j.offer(m, seq) for seq, m in enumerate(maps, start=1)] == [[s] for s in range(1, 9)]
    assert sum(j.rejected.values()) == 0
    groups = precondition(maps)
    assert [g.name for g in groups] == ["local map 1", "local map 2", "local map 3+", "local map 5", "local map 6",
                                        "local map 7", "local map 8"]
    joined = global_feature_map_of(j.state)
    assert joined is not None and np.all(np.isfinite(joined.x)) and sorted(joined.all_ids.tolist()) == [10, 11]
    np.testing.assert_allclose(joined.x, join_features_sequential([to_feature_only(g) for g in groups]).x, atol=1e-12)


def test_bad_submaps_are_rejected_and_leave_the_state_unchanged():
    maps = _maps(2)
    state = _run(maps[:3], JoinMethod.SEQUENTIAL)
    pose_only = exact_pose_graph_maps(make_world(2, 10, 0, np.random.default_rng(1)), np.random.default_rng(2))[0]
    with pytest.raises(InvalidMapError, match="holds no feature, and the map none yet: map_type feature-only joins"):
        feature_step(FeatureJoinState(), pose_only, divide_and_conquer=False)  # a pose graph is refused from the start
    with pytest.raises(InvalidMapError, match="is 3D, the global map is 2D"):
        feature_step(state, _maps(3)[0], divide_and_conquer=False)
    before = feature_result(state)
    j = Joiner(JoinMethod.SEQUENTIAL, MapType.FEATURE_ONLY)
    for seq, m in enumerate(maps[:3], start=1):
        j.offer(m, seq)
    assert j.offer(_maps(3)[0], 4) == [] and j.rejected["InvalidMapError"] == 1
    np.testing.assert_array_equal(global_feature_map_of(j.state).x, before.x)


def test_joiner_in_feature_only_mode():
    maps = _maps(2)
    j = Joiner(JoinMethod.ONLINE_DC, MapType.FEATURE_ONLY)
    for seq, m in enumerate(maps, start=1):
        assert j.offer(m, seq) == [seq]
    result = global_feature_map_of(j.state)
    batch = join_features_dc([to_feature_only(g) for g in precondition(maps)])
    np.testing.assert_array_equal(np.sort(result.all_ids), np.sort(batch.all_ids))
    with pytest.raises(InvalidMapError, match="a feature-only joiner has no pose frame"):
        global_map_of(j.state)
    with pytest.raises(InvalidMapError, match="a joiner with map_type 'as-is' has no feature-only map"):
        global_feature_map_of(Joiner(JoinMethod.SEQUENTIAL).state)
    j.reset()
    assert j.state.map_type is MapType.FEATURE_ONLY and global_feature_map_of(j.state) is None


@pytest.mark.parametrize("method", [JoinMethod.SEQUENTIAL, JoinMethod.ONLINE_DC])
def test_submaps_that_see_no_feature_are_merged_through_their_poses(method):
    """A stretch with no landmark in sight (odometry alone): such a submap was refused, the next ones were in the frame
    of a pose the map did not hold, and every later submap was refused (4 of the 8 features seen, for good)."""
    from linear_slam_ros.evaluation.synthetic import World

    rng = np.random.default_rng(1)
    poses = np.zeros((13, 3))
    poses[:, 0] = np.arange(13.0)  # a straight drive, landmarks near its start and its end only
    features = {k + 1: np.array([cx + rng.uniform(-0.3, 0.3), dy])
                for k, (cx, dy) in enumerate((cx, dy) for cx in (0.5, 1.5, 11.0, 12.0) for dy in (-2.0, 2.0, 3.0))}
    maps = noisy_local_maps(World(2, poses, features), np.random.default_rng(2), steps_per_map=1, sensor_range=3.0)
    blind = [m.name for m in maps if not np.any(m.kinds == FEATURE)]
    assert len(blind) >= 2 and maps[0].name not in blind
    j = Joiner(method, MapType.FEATURE_ONLY)
    for seq, m in enumerate(maps, start=1):
        assert j.offer(m, seq) == [seq]
    assert j.n_rejected == 0
    closed = [to_feature_only(g) for g in precondition(maps)]
    if method is JoinMethod.SEQUENTIAL:
        batch = join_features_sequential(closed)
    else:  # the binary-counter stack of the closed groups, then the open one, merged as feature_result does
        stack, counts = (), ()
        for fmap in closed[:-1]:
            stack, counts = counter_push(stack, counts, fmap, join_feature_maps)
        batch = merge_stack([*stack, closed[-1]], join_feature_maps)
    joined = global_feature_map_of(j.state)
    seen = sorted({int(i) for m in maps for i in m.ids[m.kinds == FEATURE]})
    assert sorted(joined.all_ids.tolist()) == sorted(batch.all_ids.tolist()) == seen  # every feature seen
    np.testing.assert_allclose(joined.x, batch.x, atol=1e-9)
