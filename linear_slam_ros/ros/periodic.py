"""A thread that runs a node's periodic output work, off the executor that takes the arrivals.

rclpy's ``MultiThreadedExecutor`` (Jazzy) hands every callback to a thread pool through Python
futures: with an empty callback it took 99 s to take 20,000 ``pose_graph`` messages, where the
``SingleThreadedExecutor`` took 11 s (README, "Scale"). The joiner therefore spins a single-threaded
executor for its subscriptions and services, and its long periodic work (the global map and its
views, snapshots, the summary) runs here, on wall-clock periods, never blocking an arrival.
"""

from __future__ import annotations

import contextlib
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field

FALLBACK_PERIOD = 1.0
"""s until the next run of a job whose period could not be read."""


@dataclass
class PeriodicTask:
    """One periodic job of a :class:`PeriodicThread`.

    Attributes:
        name: for the error message when ``run`` raises.
        period: returns the current period in seconds, read at each run (a parameter change
            takes effect from the next run; a period that cannot be read counts as 1 s).
        run: the job.
    """

    name: str
    period: Callable[[], float]
    run: Callable[[], None]
    due: float = field(default=0.0, repr=False)  # monotonic s of the next run


class PeriodicThread:
    """Runs :class:`PeriodicTask` jobs one after the other on one daemon thread.

    Each job runs when its period has passed since its previous start (the first run is
    immediate), or at once after :meth:`wake`. A job that raises is reported through
    ``on_error`` and runs again at its next period: the thread never dies of it.
    """

    def __init__(self, tasks: list[PeriodicTask], on_error: Callable[[str, BaseException], None], name: str) -> None:
        """Start the thread.

        Args:
            tasks: the jobs, in the order they run when several are due.
            on_error: called with the job's name and the exception it raised.
            name: the thread's name.
        """
        self._tasks = tasks
        self._on_error = on_error
        self._stop = threading.Event()
        self._wake = threading.Event()
        self._thread = threading.Thread(target=self._loop, name=name, daemon=True)
        self._thread.start()

    def wake(self) -> None:
        """Run every job now (after the one running, if any)."""
        for task in self._tasks:
            task.due = 0.0
        self._wake.set()

    def stop(self, timeout: float = 30.0) -> bool:
        """Stop after the job running, if any; return whether the thread ended within ``timeout`` s."""
        self._stop.set()
        self._wake.set()
        if self._thread is not threading.current_thread():
            self._thread.join(timeout)
        return not self._thread.is_alive()

    @property
    def alive(self) -> bool:
        """Whether the thread is running."""
        return self._thread.is_alive()

    def _report(self, name: str, exc: BaseException) -> None:
        with contextlib.suppress(Exception):  # a failing report must not end the thread
            self._on_error(name, exc)

    def _loop(self) -> None:
        while not self._stop.is_set():
            for task in self._tasks:
                if self._stop.is_set():
                    return
                now = time.monotonic()
                if now < task.due:
                    continue
                try:
                    task.due = now + task.period()
                except Exception as exc:  # noqa: BLE001 - reported; the job still runs, and again in 1 s
                    task.due = now + FALLBACK_PERIOD
                    self._report(task.name, exc)
                try:
                    task.run()
                except Exception as exc:  # noqa: BLE001 - reported, and the other jobs go on
                    self._report(task.name, exc)
            wait = min(t.due for t in self._tasks) - time.monotonic() if self._tasks else 1.0
            if wait > 0 and self._wake.wait(wait):
                self._wake.clear()
