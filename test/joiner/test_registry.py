"""The strategy registry: every (method, map type) has a strategy, and each behaves as its protocol says."""

from __future__ import annotations

import numpy as np
import pytest

from linear_slam_ros.core.errors import InvalidMapError
from linear_slam_ros.core.local_map import LocalMap
from linear_slam_ros.evaluation.synthetic import make_world, noisy_local_maps
from linear_slam_ros.feature_only.maps import FeatureMap
from linear_slam_ros.joiner.registry import STRATEGIES, get_strategy, methods
from linear_slam_ros.joiner.strategy import PER_JOIN, PER_LEVEL, PER_SUBMAP, JoinMethod, MapType


def test_every_method_and_map_type_has_a_strategy():
    assert set(STRATEGIES) == {(m, t) for m in JoinMethod for t in MapType}
    for (method, map_type), strategy in STRATEGIES.items():
        assert (strategy.method, strategy.map_type) == (method, map_type)
        assert strategy.result_type is (FeatureMap if map_type is MapType.FEATURE_ONLY else LocalMap)
        assert strategy.run_step in (PER_SUBMAP, PER_JOIN, PER_LEVEL)
    assert get_strategy(JoinMethod.DC).run_step == PER_LEVEL  # pose maps: a level's joins are done together
    assert methods(MapType.AS_IS, online_only=True) == (JoinMethod.SEQUENTIAL, JoinMethod.ONLINE_DC)
    assert methods(MapType.FEATURE_ONLY, online_only=False) == tuple(JoinMethod)


def test_unknown_keys_are_refused():
    with pytest.raises(ValueError, match="'online_dc' is not a valid JoinMethod"):
        get_strategy("online_dc")
    with pytest.raises(ValueError, match="'features' is not a valid MapType"):
        get_strategy("sequential", "features")


@pytest.fixture(scope="module")
def maps():
    world = make_world(2, 24, 30, np.random.default_rng(5))
    return noisy_local_maps(world, np.random.default_rng(6), steps_per_map=3, sensor_range=7.0)


@pytest.mark.parametrize("key", sorted(STRATEGIES, key=str))
def test_stepping_equals_running_and_steps_are_pure(key, maps):
    strategy = STRATEGIES[key]
    state = strategy.empty()
    assert strategy.result(state) is None
    states = [state]
    for m in maps:
        states.append(strategy.step(states[-1], m))
    stepped = strategy.result(states[-1])
    again = strategy.result(states[len(maps) // 2])  # an earlier state is still valid after later steps
    ran, steps = strategy.run(maps)
    np.testing.assert_allclose(stepped.x, ran.x, rtol=0, atol=1e-9)
    assert again.state_dim < stepped.state_dim
    assert len(steps) == (len(maps) if strategy.run_step == PER_SUBMAP else len(steps)) and all(s >= 0 for s in steps)


def test_running_nothing_is_an_error():
    with pytest.raises(InvalidMapError, match="no joined map: the 0 local maps gave none"):
        get_strategy(JoinMethod.ONLINE_DC).run([])


@pytest.mark.parametrize("key", sorted(STRATEGIES, key=str))
def test_holds_answers_for_the_joined_maps_variables_and_frame_pose(key, maps):
    strategy = STRATEGIES[key]
    state = strategy.empty()
    for m in maps[:7]:
        state = strategy.step(state, m)
    as_keys = lambda *ks: np.array(ks, dtype=np.int64)  # noqa: E731
    if strategy.holds(state, as_keys(2)) is None:  # strategies that cannot tell cheaply say so for every question
        assert strategy.holds(state, as_keys()) is None
        assert key not in ((JoinMethod.SEQUENTIAL, MapType.AS_IS), (JoinMethod.ONLINE_DC, MapType.AS_IS))
        return
    joined = strategy.result(state)
    later = {int(k) for m in maps[7:] for k in m.keys} - set(joined.keys.tolist()) - {2 * joined.frame_id}
    assert later, "the fixture's later submaps see something new"
    unknown = sorted(later)[:3]
    assert all(strategy.holds(state, as_keys(int(k))) for k in joined.keys)
    assert strategy.holds(state, as_keys(2 * joined.frame_id))  # the map's frame pose is no variable, but it is held
    assert strategy.holds(state, as_keys(*unknown, int(joined.keys[-1])))  # any of them
    assert not strategy.holds(state, as_keys(*unknown))
    assert not strategy.holds(state, as_keys())
