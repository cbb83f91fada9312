"""The output thread of the joiner (linear_slam_ros.ros.periodic): periods, wake, errors, stop."""

from __future__ import annotations

import threading
import time

from linear_slam_ros.ros.periodic import PeriodicTask, PeriodicThread
from support import wait_until


def test_jobs_run_at_once_then_at_their_period() -> None:
    times: list[float] = []
    start = time.monotonic()
    thread = PeriodicThread([PeriodicTask("tick", lambda: 0.05, lambda: times.append(time.monotonic()))], print, "t")
    try:
        assert wait_until(lambda: len(times) >= 5)
    finally:
        assert thread.stop()
    assert times[0] - start < 0.04  # the first run does not wait for a period
    gaps = [b - a for a, b in zip(times, times[1:], strict=False)]
    assert min(gaps) >= 0.045  # never early
    assert not thread.alive


def test_the_period_is_read_before_each_wait() -> None:
    period = [10.0]
    runs: list[float] = []
    thread = PeriodicThread([PeriodicTask("tick", lambda: period[0], lambda: runs.append(time.monotonic()))], print, "t")
    try:
        assert wait_until(lambda: len(runs) == 1)
        period[0] = 0.02
        time.sleep(0.1)
        assert len(runs) == 1  # the 10 s wait already begun is not cut short...
        thread.wake()  # ...but after the next run the new period holds
        assert wait_until(lambda: len(runs) >= 4, timeout=2.0)
    finally:
        thread.stop()


def test_wake_runs_every_job_now_and_first_due_delays_a_job() -> None:
    runs = {"a": 0, "b": 0}

    def run(name: str):
        return lambda: runs.__setitem__(name, runs[name] + 1)

    late = time.monotonic() + 60.0
    thread = PeriodicThread([PeriodicTask("a", lambda: 60.0, run("a")), PeriodicTask("b", lambda: 60.0, run("b"), late)],
                            print, "t")
    try:
        assert wait_until(lambda: runs["a"] == 1)
        time.sleep(0.05)
        assert runs == {"a": 1, "b": 0}  # b's first run is a minute away
        thread.wake()
        assert wait_until(lambda: runs == {"a": 2, "b": 1})
    finally:
        thread.stop()


def test_a_job_that_raises_is_reported_and_the_others_go_on() -> None:
    errors: list[tuple[str, str]] = []
    ok = [0]

    def boom() -> None:
        raise ValueError("bad output")

    thread = PeriodicThread(
        [PeriodicTask("boom", lambda: 0.01, boom), PeriodicTask("ok", lambda: 0.01, lambda: ok.__setitem__(0, ok[0] + 1))],
        lambda name, exc: errors.append((name, str(exc))), "t",
    )
    try:
        assert wait_until(lambda: len(errors) >= 3 and ok[0] >= 3)
        assert thread.alive
    finally:
        thread.stop()
    assert set(errors) == {("boom", "bad output")}


def test_stop_waits_for_the_running_job_and_leaves_no_thread() -> None:
    started, release = threading.Event(), threading.Event()
    done: list[bool] = []

    def slow() -> None:
        started.set()
        release.wait(5.0)
        done.append(True)

    thread = PeriodicThread([PeriodicTask("slow", lambda: 0.01, slow)], print, "t-slow")
    assert started.wait(5.0)
    assert not thread.stop(timeout=0.05)  # still in the job
    release.set()
    assert thread.stop()
    assert done == [True]
    assert not any(t.name == "t-slow" for t in threading.enumerate())


def test_a_period_that_cannot_be_read_is_reported_and_the_job_runs_every_second() -> None:
    errors: list[str] = []
    runs: list[float] = []

    def period() -> float:
        raise ZeroDivisionError("publish_rate 0")

    thread = PeriodicThread([PeriodicTask("publish", period, lambda: runs.append(time.monotonic()))],
                            lambda name, exc: errors.append(f"{name}: {exc}"), "t")
    try:
        assert wait_until(lambda: len(runs) >= 2, timeout=3.0)
        assert thread.alive
    finally:
        thread.stop()
    assert errors[0] == "publish: publish_rate 0"
    assert runs[1] - runs[0] >= 0.95  # the fallback period
