"""The online refiner in a process of its own, so that it never takes the joiner's interpreter lock.

:class:`RefineWorker` starts a process (``spawn``: a fresh interpreter, nothing inherited from
the threads of the parent) running :func:`serve`: it takes submissions and linear estimates from
a queue, runs :class:`~linear_slam_ros.refinement.online.OnlineRefiner` one Gauss-Newton step at a
time, reads the queue between steps (new submaps are taken in mid-round when due; a round that
ended at ``streaming_rtol`` while submaps arrived resumes once none has come for ``settle_s``), and hands
each refined map to a sink: after a round converges, at most every ``publish_period`` s while
one runs, and once the stream is idle (nothing queued, nothing arrived for ``idle_s``) after
every step that lowered χ² by at most :data:`NEAR_OPTIMUM` (the last submaps' map is out as soon
as it is within about 0.1% of the optimum, not the last steps later). The sink
is built in the child from a :class:`SinkSpec` (an importable factory and its keyword
arguments): the node's publishes ``global_map_refined`` through rclpy
(``linear_slam_ros.ros.refine_sink``); :func:`queue_sink` sends the values back to the parent.

Stopping (:meth:`RefineWorker.stop`, also on reset) asks the child to end after the step under
way, waits for it, and only terminates it if it does not end within the timeout. The child also
ends when its parent dies, and ignores SIGINT (a terminal's Ctrl-C reaches the whole process
group; the parent decides).
"""

from __future__ import annotations

import contextlib
import dataclasses
import importlib
import logging
import math
import multiprocessing
import multiprocessing.queues
import os
import queue
import signal
import sys
import time
import types
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Any, Protocol

from linear_slam_ros.core.errors import ConfigError
from linear_slam_ros.refinement.online import LinearEstimate, OnlineRefiner, RefinedMap, RefinerConfig, Submission

logger = logging.getLogger(__name__)

PARENT_POLL_S = 1.0
"""s, how often an idle child checks that its parent still runs."""

REFINER_NICE = 10
"""How much lower the child's CPU priority is than the node's (``os.nice``): on a machine with fewer
cores than busy threads, joining takes the CPU first (a nice-10 process gets about a tenth of a
core that a nice-0 thread also wants), and the refiner uses what joining leaves."""

NEAR_OPTIMUM = 1e-3
"""Once the stream is idle, a step that lowers χ² by at most this fraction is published (Gauss-Newton's
next decrease is far smaller: the map is within about this fraction of the optimum)."""


class Sink(Protocol):
    """Where the child hands refined maps (built in the child by a :class:`SinkSpec`)."""

    def publish(self, refined: RefinedMap, cpu_seconds: float) -> None:
        """Hand over a refined map (``cpu_seconds``: the child's CPU time so far)."""

    def close(self, cpu_seconds: float) -> None:
        """Release what the sink holds; the child ends next."""

    def configure(self, settings: dict[str, Any]) -> None:
        """Change some of the factory's keyword arguments (:meth:`RefineWorker.configure_sink`)."""


@dataclass(frozen=True)
class SinkSpec:
    """An importable sink factory ``"package.module:function"`` and its keyword arguments (picklable)."""

    factory: str
    kwargs: dict[str, Any] = field(default_factory=dict)

    def build(self) -> Sink:
        """Import the factory and call it.

        Raises:
            ConfigError: the factory is not ``module:function`` or cannot be imported.
        """
        module, _, name = self.factory.partition(":")
        if not module or not name:
            raise ConfigError(f"sink factory {self.factory!r} is not 'module:function'")
        try:
            factory = getattr(importlib.import_module(module), name)
        except (ImportError, AttributeError) as exc:
            raise ConfigError(f"sink factory {self.factory!r} cannot be imported: {exc}") from None
        sink: Sink = factory(**self.kwargs)
        return sink


@dataclass(frozen=True)
class Published:
    """What :func:`queue_sink` sends back: a refined map, the publication time and the child's CPU time.

    Attributes:
        refined: the refined map (with or without information, as the sink was asked).
        published_at: ``time.monotonic()`` s when it was handed over.
        cpu_seconds: CPU time of the child so far, s.
        final: the child's last word (``refined`` is ``None``): it is closing.
    """

    refined: RefinedMap | None
    published_at: float
    cpu_seconds: float
    final: bool = False


class _QueueSink:
    def __init__(self, out: multiprocessing.queues.Queue[Published], information: bool) -> None:
        self.out = out
        self.information = information

    def publish(self, refined: RefinedMap, cpu_seconds: float) -> None:
        self.out.put(Published(refined, time.monotonic(), cpu_seconds))

    def close(self, cpu_seconds: float) -> None:
        self.out.put(Published(None, time.monotonic(), cpu_seconds, final=True))
        self.out.close()
        self.out.join_thread()

    def configure(self, settings: dict[str, Any]) -> None:
        """Nothing to change: the refined maps go back as they are."""


def queue_sink(out: multiprocessing.queues.Queue[Published], information: bool = False) -> Sink:
    """A sink that puts :class:`Published` values on ``out`` (a queue of the worker's context)."""
    return _QueueSink(out, information)


def serve(
    inbox: multiprocessing.queues.Queue[Any], sink_spec: SinkSpec, config: RefinerConfig, information: bool = True,
    ready: Any = None,
) -> None:
    """The child's loop (module docstring): refine, read the inbox between steps, publish, until told to stop.

    ``ready`` (a ``multiprocessing`` event) is set once the sink is built: the child is up.
    """
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    from linear_slam_ros.core.runtime import SHARED_MACHINE_BLAS_THREADS, set_blas_threads

    set_blas_threads(SHARED_MACHINE_BLAS_THREADS)  # the joiner has the other core
    try:
        os.nice(REFINER_NICE)  # joining first (REFINER_NICE)
    except OSError as exc:  # a platform or a limit that refuses it: the refiner runs at the node's priority
        logger.warning("refiner: cannot lower its CPU priority: %s", exc)
    parent = os.getppid()
    sink = sink_spec.build()
    if ready is not None:
        ready.set()
    refiner = OnlineRefiner(config)
    last_published = -math.inf
    running = True
    try:
        while running:
            busy = not refiner.converged
            due = refiner.seconds_until_due()
            due_in = math.inf if due is None else due
            if not refiner.settled:  # a round ended at streaming_rtol resumes once the stream has settled
                due_in = min(due_in, refiner.seconds_until_settled())
            timeout = 0.0 if busy else min(due_in, PARENT_POLL_S)
            messages = _drain(inbox, timeout)
            for kind, payload in messages:
                if kind == "stop":
                    running = False
                    break
                if kind == "submit":
                    refiner.submit(payload)
                elif kind == "linear":
                    refiner.linear(payload)
                elif kind == "sink":
                    try:
                        sink.configure(payload)
                    except Exception as exc:  # noqa: BLE001 - a setting the sink refuses does not end the refiner
                        logger.warning("refiner: the sink refused %s: %s: %s", payload, type(exc).__name__, exc)
            if not running:
                break
            if not messages and os.getppid() != parent:
                logger.warning("refiner: the parent process ended; stopping")
                break
            if refiner.absorb_due():
                refiner.absorb()
            else:
                refiner.resume()
            if not refiner.converged:
                converged = refiner.iterate()
                now = time.monotonic()
                # once the stream is idle a step that lowered χ² by under NEAR_OPTIMUM goes out: the map
                # within about 0.1% of the optimum is published at once, not the last steps later
                near = refiner.stream_idle() and refiner.last_relative_decrease <= NEAR_OPTIMUM
                if converged or near or now - last_published >= config.publish_period:
                    sink.publish(refiner.result(information), time.process_time())
                    last_published = time.monotonic()
    finally:
        sink.close(time.process_time())


def _drain(inbox: multiprocessing.queues.Queue[Any], timeout: float) -> list[tuple[str, Any]]:
    """Every message waiting (blocking up to ``timeout`` s for the first)."""
    out: list[tuple[str, Any]] = []
    try:
        out.append(inbox.get(timeout=timeout) if timeout > 0 else inbox.get_nowait())
        while True:
            out.append(inbox.get_nowait())
    except queue.Empty:
        pass
    return out


@contextlib.contextmanager
def _main_module_hidden() -> Iterator[None]:
    """Hide the parent's ``__main__`` from ``spawn`` while a child starts.

    ``spawn`` runs the parent's main module again in the child (as ``__mp_main__``) so that
    objects pickled from it resolve there. Everything the refiner's child is given lives in this
    package (``serve``, a :class:`SinkSpec` naming its factory by module), so that import is
    pure start-up cost: the node's or the race's whole module graph (the joiner, the gate and
    ``scipy.special``, rclpy), 0.2-0.4 s of CPU. With a main module that has neither ``__spec__``
    nor ``__file__``, ``spawn`` imports none.
    """
    main = sys.modules.get("__main__")
    sys.modules["__main__"] = types.ModuleType("__main__")
    try:
        yield
    finally:
        if main is not None:
            sys.modules["__main__"] = main


class RefineWorker:
    """Owner of the refiner's process (started at construction; module docstring).

    Args:
        sink: what the child publishes refined maps to.
        config: the refiner's settings.
        information: publish refined maps with their information ``J^T W J``.
    """

    def __init__(self, sink: SinkSpec, config: RefinerConfig | None = None, information: bool = True) -> None:
        self.sink = sink
        self.config = config or RefinerConfig()
        self.information = information
        self._ctx = multiprocessing.get_context("spawn")
        self._inbox: multiprocessing.queues.Queue[Any] | None = None
        self._process: multiprocessing.process.BaseProcess | None = None
        self._ready: Any = None  # the child's event: set once it is up
        self.exitcodes: list[int | None] = []  # of every process stopped so far, in order
        self.start()

    @property
    def context(self) -> Any:
        """The multiprocessing context (make a :func:`queue_sink`'s queue with it)."""
        return self._ctx

    @property
    def alive(self) -> bool:
        """Whether the child runs."""
        return self._process is not None and self._process.is_alive()

    @property
    def pid(self) -> int | None:
        """The child's process id."""
        return None if self._process is None else self._process.pid

    def start(self) -> None:
        """Start a child (a no-op while one runs)."""
        if self.alive:
            return
        self._inbox = self._ctx.Queue()
        self._ready = self._ctx.Event()
        self._process = self._ctx.Process(
            target=serve, args=(self._inbox, self.sink, self.config, self.information, self._ready),
            name="linear_slam_refiner",
            daemon=True,
        )
        with _main_module_hidden():
            self._process.start()

    def wait_ready(self, timeout: float) -> bool:
        """Wait up to ``timeout`` s for the child to be up (imports done, sink built); return whether it is."""
        return self._ready is not None and bool(self._ready.wait(timeout))

    def submit(self, submission: Submission) -> None:
        """Send a joined submap to the child."""
        if self._inbox is not None:
            self._inbox.put(("submit", submission))

    def linear(self, estimate: LinearEstimate) -> None:
        """Send the newest linear estimate to the child."""
        if self._inbox is not None:
            self._inbox.put(("linear", estimate))

    def configure_sink(self, **settings: Any) -> None:
        """Change some of the sink factory's keyword arguments: the child's sink takes them at once (its
        ``configure``), and a child started later (:meth:`reset`) is built with them."""
        self.sink = dataclasses.replace(self.sink, kwargs={**self.sink.kwargs, **settings})
        if self._inbox is not None:
            self._inbox.put(("sink", settings))

    def stop(self, timeout: float = 10.0) -> int | None:
        """Ask the child to end after its current step, wait, terminate it past ``timeout`` s (idempotent).

        Returns:
            The child's exit code (0: it ended cleanly), ``None`` without a child.
        """
        process, inbox = self._process, self._inbox
        if process is None or inbox is None:
            return None
        self._process = self._inbox = None
        if process.is_alive():
            inbox.put(("stop", None))
            process.join(timeout)
            if process.is_alive():
                logger.warning("refiner process %s still busy after %.0f s: terminated", process.pid, timeout)
                process.terminate()
                process.join(5.0)
        inbox.cancel_join_thread()  # what the child did not read is dropped
        inbox.close()
        self.exitcodes.append(process.exitcode)
        return process.exitcode

    def reset(self, timeout: float = 10.0) -> int | None:
        """Stop the child (its submaps and solution go with it) and start a fresh one.

        Returns:
            The stopped child's exit code.
        """
        code = self.stop(timeout)
        self.start()
        return code
