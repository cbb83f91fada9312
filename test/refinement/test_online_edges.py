"""The online refiner's schedule at its edges: failed steps, rounds over new submaps, idle and settle times,
linear estimates in order. (Found by a mutation audit: each test fails on a mutant the suite let through.)
"""

from __future__ import annotations

import numpy as np
import pytest

from linear_slam_ros.core import least_squares
from linear_slam_ros.core.errors import ConfigError, SolverError
from linear_slam_ros.evaluation.runner import run_join
from linear_slam_ros.evaluation.synthetic import make_world, noisy_local_maps
from linear_slam_ros.joiner.config import OutputFrame
from linear_slam_ros.joiner.joiner import Joiner, global_result
from linear_slam_ros.joiner.strategy import JoinMethod
from linear_slam_ros.refinement.online import LinearEstimate, OnlineRefiner, RefinerConfig, Submission, refine_offline
from support import FakeClock


@pytest.fixture(scope="module")
def maps():
    w = make_world(2, 36, 60, np.random.default_rng(1))
    return noisy_local_maps(w, np.random.default_rng(2), steps_per_map=3)


def _absorbed(maps, n, config=None, clock=None):
    r = OnlineRefiner(config or RefinerConfig(), clock or FakeClock())
    for seq, m in enumerate(maps[:n], start=1):
        r.submit(Submission(seq, m, 0.0))
    r.absorb()
    return r


def _linear(maps, n, count=None):
    j = Joiner(JoinMethod.ONLINE_DC)
    for seq, m in enumerate(maps[:n], start=1):
        j.offer(m, seq)
    return LinearEstimate.of_map(global_result(j.state, OutputFrame.FIRST_POSE), count if count is not None else n)


def test_chi2_rtol_of_one_is_refused():
    with pytest.raises(ConfigError):
        RefinerConfig(chi2_rtol=1.0)


def test_a_failed_step_ends_the_round_settled(maps, monkeypatch):
    r = _absorbed(maps, 5)
    monkeypatch.setattr(least_squares, "gauss_newton_step", lambda *a, **k: (_ for _ in ()).throw(SolverError("x")))
    assert r.iterate() and r.settled and r.result().converged and not r.resume()


def test_a_round_over_new_submaps_is_not_reported_converged_before_it_runs(maps):
    r = _absorbed(maps, 5, RefinerConfig(streaming_rtol=0.0))
    while not r.iterate():
        pass
    assert r.result().converged
    r.submit(Submission(6, maps[5], 0.0))
    r.absorb()
    assert not r.result().converged


def test_seconds_until_due_is_never_negative(maps):
    c = FakeClock()
    r = OnlineRefiner(RefinerConfig(idle_s=0.05), c)
    r.submit(Submission(1, maps[0], 0.0))
    c.t = 10.0
    assert r.seconds_until_due() == 0.0


def test_queued_submaps_are_due_mid_round_once_the_stream_is_idle(maps):
    c = FakeClock()
    r = _absorbed(maps, 10, RefinerConfig(idle_s=0.05, growth=0.25), c)
    r.iterate()
    assert not r.converged
    r.submit(Submission(11, maps[10], c.t))
    assert not r.absorb_due()
    c.t += 0.1
    assert r.absorb_due()


def test_queued_is_not_idle(maps):
    c = FakeClock()
    r = OnlineRefiner(RefinerConfig(idle_s=0.05), c)
    r.submit(Submission(1, maps[0], 0.0))
    c.t = 1.0
    assert not r.stream_idle()


def test_settled_waits_for_idle_s_when_settle_s_is_shorter(maps):
    c = FakeClock()
    r = OnlineRefiner(RefinerConfig(idle_s=1.0, settle_s=0.1), c)
    r.submit(Submission(1, maps[0], 0.0))
    r.absorb()
    assert r.seconds_until_settled() == pytest.approx(1.0)


def test_a_resumed_round_gets_its_full_iteration_budget(maps):
    r = _absorbed(maps, 12, RefinerConfig(max_round_iterations=2, chi2_rtol=1e-15, step_tol=0.0, settle_s=0.0, idle_s=0.0))
    assert r.iterate() is False and r.iterate() is True and not r.settled
    assert r.resume()
    steps = 1
    while not r.iterate():
        steps += 1
    assert steps == 2 or r.settled


def test_a_submission_without_end_pose_keeps_the_end(maps):
    r = OnlineRefiner(RefinerConfig())
    r.submit(Submission(1, maps[0], 0.0))
    r.submit(Submission(2, maps[1].replace(end_id=None), 0.0, extra=True))
    r.absorb()
    assert r.result(information=False).map.end_id == maps[0].end_id


def test_a_feature_id_above_every_pose_id_is_never_the_anchor(maps):
    r = _absorbed(maps, 2)
    r.linear(_linear(maps, 3))
    r.submit(Submission(3, maps[2], 0.0))
    r.absorb()  # KeyError with a feature as anchor


def test_the_newest_linear_estimate_places_parked_submaps(maps):
    r = _absorbed(maps, 4)
    r.submit(Submission(6, maps[5], 0.0))  # submap 5 lost: its frame pose is unknown
    r.absorb()
    assert r.n_parked == 1
    r.linear(_linear(maps, 4, count=5))
    r.linear(_linear(maps, 6, count=5))  # same count, more of the map (a closure linked it): taken
    assert r.n_pending == 1 and r.absorb() == 1


def test_an_older_linear_estimate_is_ignored(maps):
    r = _absorbed(maps, 4)
    r.linear(_linear(maps, 6))
    r.linear(_linear(maps, 4))
    r.submit(Submission(6, maps[5], 0.0))
    assert r.absorb() == 1 and r.n_parked == 0


def test_refine_offline_starts_from_the_linear_map(maps):
    lin = run_join(maps[:12], "online-dc").result
    a = refine_offline(maps[:12], lin)
    b = refine_offline(maps[:12], None)
    assert a.initial_chi2 < b.initial_chi2
