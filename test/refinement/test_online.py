"""The online refiner: streamed with warm starts it reaches the offline Gauss-Newton optimum; its errors."""

from __future__ import annotations

import math

import numpy as np
import pytest

import linear_slam_ros.evaluation.city  # noqa: F401 - registers synthetic:NAME
from linear_slam_ros.core.errors import ConfigError, InvalidMapError
from linear_slam_ros.core.local_map import LocalMap
from linear_slam_ros.evaluation.nonlinear import refine
from linear_slam_ros.evaluation.objective import chi2
from linear_slam_ros.evaluation.runner import run_join
from linear_slam_ros.io.datasets import read_dataset
from linear_slam_ros.joiner.config import OutputFrame
from linear_slam_ros.joiner.joiner import Joiner, global_result
from linear_slam_ros.joiner.strategy import JoinMethod
from linear_slam_ros.refinement.online import (
    LinearEstimate,
    OnlineRefiner,
    RefinerConfig,
    Submission,
    refine_offline,
)
from linear_slam_ros.refinement.worker import SinkSpec


@pytest.fixture(scope="module")
def city() -> tuple[LocalMap, ...]:
    return read_dataset("synthetic:city2d-300@3").maps


class FakeClock:
    def __init__(self) -> None:
        self.t = 0.0

    def __call__(self) -> float:
        return self.t


def test_streamed_refinement_equals_offline_refine(city: tuple[LocalMap, ...]) -> None:
    """Submaps one by one, linear estimates now and then, rounds interrupted by growth: at the end of the
    stream the refined χ² equals the offline refine's to 1e-8 (relative), and it is below the linear χ²."""
    clock = FakeClock()
    refiner = OnlineRefiner(RefinerConfig(growth=0.25, idle_s=0.05), clock)
    joiner = Joiner(JoinMethod.ONLINE_DC)
    rounds = 0
    for seq, m in enumerate(city, start=1):
        assert joiner.offer(m, seq) == [seq]
        clock.t += 0.001
        refiner.submit(Submission(seq, m, clock.t))
        if seq % 40 == 0:
            linear = global_result(joiner.state, OutputFrame.FIRST_POSE)
            refiner.linear(LinearEstimate.of_map(linear, seq))
        if refiner.absorb_due():
            refiner.absorb()
            rounds += 1
        refiner.iterate()  # one step between arrivals: rounds restart before they converge
    assert 5 < rounds < 40  # geometric: not one round per submap
    clock.t += 1.0  # the stream has ended: what is queued is due
    assert refiner.absorb_due()
    refiner.absorb()
    while not refiner.iterate():
        pass
    result = refiner.result()
    assert result.n_submaps == len(city) and result.converged and result.last_seq == len(city)
    offline = refine(run_join(city, "online-dc").result, city)
    assert abs(result.chi2 - offline.chi2) <= 1e-8 * offline.chi2
    assert abs(chi2(result.map, city) - offline.chi2) <= 1e-8 * offline.chi2  # the project's χ² of the map agrees
    assert result.chi2 < offline.chi2_history[0]  # below the linear map's


def test_refine_offline_from_linear_and_from_chaining_agree(city: tuple[LocalMap, ...]) -> None:
    linear = run_join(city[:120], "online-dc").result
    from_linear = refine_offline(city[:120], linear, RefinerConfig(chi2_rtol=1e-12))
    chained = refine_offline(city[:120], None, RefinerConfig(chi2_rtol=1e-12))
    assert from_linear.iterations <= chained.iterations
    assert abs(from_linear.chi2 - chained.chi2) <= 1e-8 * chained.chi2
    np.testing.assert_allclose(from_linear.map.x, chained.map.x, atol=1e-6)
    assert from_linear.map.info.shape == (from_linear.map.state_dim,) * 2


def _round_on(city: tuple[LocalMap, ...], config: RefinerConfig, clock: FakeClock) -> OnlineRefiner:
    """A refiner that has absorbed ``city`` from its chained warm start, the last submap just arrived."""
    refiner = OnlineRefiner(config, clock)
    for seq, m in enumerate(city, start=1):
        refiner.submit(Submission(seq, m, clock.t))
    refiner.absorb()
    return refiner


def test_a_round_ends_early_while_submaps_arrive_and_resumes_once_settled(city: tuple[LocalMap, ...]) -> None:
    """While submaps arrive a round ends at streaming_rtol (not settled, reported not converged); once none
    has come for settle_s it resumes to chi2_rtol and reaches the same χ² as a round that never stopped."""
    maps = city[:150]
    clock = FakeClock()
    tight = _round_on(maps, RefinerConfig(idle_s=0.05, streaming_rtol=0.0), clock)
    while not tight.iterate():
        pass
    early = _round_on(maps, RefinerConfig(idle_s=0.05, settle_s=0.5, streaming_rtol=1e-2), clock)
    while not early.iterate():  # the clock stands still: submaps are still arriving
        pass
    assert early.converged and not early.settled and not early.result().converged
    assert early.iterations < tight.iterations
    assert early.last_relative_decrease <= 1e-2
    assert not early.resume() and early.seconds_until_settled() == pytest.approx(0.5)
    clock.t += 0.1  # idle (queued submaps would be taken in), not settled: a pause of the stream
    assert early.stream_idle() and not early.resume()
    clock.t += 0.4
    assert early.seconds_until_settled() == 0.0 and early.resume() and not early.converged
    while not early.iterate():
        pass
    assert early.settled and early.result().converged and not early.resume()
    assert abs(early.chi2 - tight.chi2) <= 1e-8 * tight.chi2
    assert tight.settled and tight.result().converged
    early.submit(Submission(len(maps) + 1, city[len(maps)], clock.t))
    assert early.seconds_until_settled() == math.inf  # queued: taken in first


def test_errors_name_the_bad_value(city: tuple[LocalMap, ...]) -> None:
    with pytest.raises(ConfigError, match="refiner growth=0"):
        RefinerConfig(growth=0)
    with pytest.raises(ConfigError, match="refiner streaming_rtol=1.0"):
        RefinerConfig(streaming_rtol=1.0)
    with pytest.raises(ConfigError, match="refiner settle_s=nan"):
        RefinerConfig(settle_s=float("nan"))
    with pytest.raises(ConfigError, match="refiner max_round_iterations=0"):
        RefinerConfig(max_round_iterations=0)
    with pytest.raises(InvalidMapError, match="holds no submap yet"):
        OnlineRefiner().result()
    with pytest.raises(InvalidMapError, match="no submaps to refine"):
        refine_offline([])
    with pytest.raises(ConfigError, match="'nomodule' is not 'module:function'"):
        SinkSpec("nomodule").build()
    with pytest.raises(ConfigError, match="cannot be imported"):
        SinkSpec("linear_slam_ros.refinement.worker:no_such_sink").build()


def test_a_submap_that_cannot_be_placed_is_left_out(city: tuple[LocalMap, ...]) -> None:
    refiner = OnlineRefiner()
    refiner.submit(Submission(1, city[0], 0.0))
    refiner.submit(Submission(2, city[10], 0.0))  # its frame pose is not in the map yet
    assert refiner.absorb() == 1
    assert refiner.n_skipped == 1 and refiner.n_absorbed == 1


def test_an_extra_measurement_is_absorbed_but_not_counted_as_a_submap(city: tuple[LocalMap, ...]) -> None:
    refiner = OnlineRefiner()
    refiner.submit(Submission(1, city[0], 0.0))
    refiner.submit(Submission(2, city[1], 0.0))
    refiner.submit(Submission(2, city[1], 0.0, extra=True))  # a closure released with submap 2 (here: the same edges again)
    assert refiner.absorb() == 3 and refiner.n_absorbed == 3
    while not refiner.iterate():
        pass
    assert refiner.result().n_submaps == 2
