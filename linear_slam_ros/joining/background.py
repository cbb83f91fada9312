"""A background worker that computes deferred joins ahead of the arrivals that would wait for them.

Online divide and conquer defers its large merges (:class:`~linear_slam_ros.joining.divide_conquer.Deferred`);
the worker computes them in the order they were deferred, on its own thread, while the thread
that receives submaps goes on joining the small newest levels. The heavy parts of a join
(sparse Cholesky, BLAS, scipy's sparse kernels) release the interpreter lock, so the two threads
share the cores. Whoever needs a deferred join before the worker reaches it computes it
itself: the worker only makes results ready sooner, never different.
"""

from __future__ import annotations

import logging
import queue
import threading
import time

from linear_slam_ros.core.errors import LinearSlamError
from linear_slam_ros.joining.divide_conquer import Deferred

logger = logging.getLogger(__name__)


class MergeWorker:
    """One thread computing :class:`Deferred` joins in submission order.

    Attributes:
        seconds: wall time spent computing joins, s.
        n_done: joins computed by the worker.
    """

    def __init__(self, name: str = "linear_slam_merge") -> None:
        self._queue: queue.SimpleQueue[tuple[int, Deferred] | None] = queue.SimpleQueue()
        self._submitted: set[int] = set()  # ids of the queued joins (kept alive by the queue)
        self._generation = 0  # bumped by clear(): older queued joins are dropped
        self._lock = threading.Lock()
        self._outstanding = 0  # queued or under way
        self.seconds = 0.0
        self.n_done = 0
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self._thread.start()

    @property
    def alive(self) -> bool:
        """Whether the worker thread runs."""
        return self._thread.is_alive()

    def submit(self, joins: list[Deferred]) -> None:
        """Queue joins not queued yet (inputs before results, as :func:`pending_joins` lists them)."""
        with self._lock:
            for d in joins:
                if id(d) not in self._submitted and not d.done and not d.failed:
                    self._submitted.add(id(d))
                    self._outstanding += 1
                    self._queue.put((self._generation, d))

    def clear(self) -> None:
        """Drop the queued joins (after a reset: nobody needs them); a join under way finishes."""
        with self._lock:
            self._generation += 1
            self._submitted.clear()

    def idle(self) -> bool:
        """Whether nothing is queued or under way."""
        with self._lock:
            return self._outstanding == 0

    def wait_idle(self, timeout: float) -> bool:
        """Wait until :meth:`idle` (at most ``timeout`` s); return whether it is."""
        deadline = time.monotonic() + timeout
        while not self.idle():
            if time.monotonic() > deadline:
                return False
            time.sleep(0.001)
        return True

    def stop(self, timeout: float = 30.0) -> None:
        """Drop the queue, let a join under way finish, and end the thread (idempotent)."""
        self.clear()
        self._queue.put(None)
        self._thread.join(timeout)
        if self._thread.is_alive():  # pragma: no cover - a join longer than the timeout
            logger.warning("merge worker still busy after %.0f s; it is a daemon thread and ends with the process", timeout)

    def _run(self) -> None:
        while True:
            item = self._queue.get()
            if item is None:
                return
            generation, join = item
            with self._lock:
                self._submitted.discard(id(join))
                current = generation == self._generation
            t0 = time.perf_counter()
            try:
                # counted and timed only when this thread computed it (not one the publisher or the gate made)
                made = join.compute() if current else 0
                if made:
                    self.n_done += made
                    self.seconds += time.perf_counter() - t0
            except LinearSlamError as exc:  # raised again to whoever asks for the value
                logger.warning("deferred join failed: %s", exc)
            except Exception:  # noqa: BLE001 - any other (a MemoryError of a large merge): the worker goes on
                logger.exception("deferred join failed unexpectedly; whoever asks for its value computes it again")
            finally:
                with self._lock:
                    self._outstanding -= 1
