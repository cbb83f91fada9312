"""Timing figures shared by the joiner, the CLI and the benchmark: latency percentiles, peak RSS."""

from __future__ import annotations

import resource
from collections.abc import Sequence
from pathlib import Path
from typing import NamedTuple

import numpy as np


class Latency(NamedTuple):
    """p50, p99 and maximum of a set of durations, in milliseconds (0 when there is none)."""

    p50_ms: float
    p99_ms: float
    max_ms: float


def latency(seconds: Sequence[float]) -> Latency:
    """Return the p50, p99 and maximum of durations given in seconds, in milliseconds."""
    ms = np.asarray(seconds, dtype=np.float64) * 1e3
    if ms.size == 0:
        return Latency(0.0, 0.0, 0.0)
    p50, p99 = np.percentile(ms, [50, 99])
    return Latency(float(p50), float(p99), float(ms.max()))


def latency_summary(seconds: Sequence[float]) -> dict[str, float]:
    """Return the report keys ``per_submap_ms_p50/p99/max`` of per-step durations (seconds)."""
    lat = latency(seconds)
    return {"per_submap_ms_p50": lat.p50_ms, "per_submap_ms_p99": lat.p99_ms, "per_submap_ms_max": lat.max_ms}


def reset_peak_rss(clear_refs: Path = Path("/proc/self/clear_refs")) -> bool:
    """Reset this process's peak resident set size to its current one, so that :func:`peak_rss_mb`
    reads the peak of what runs next (Linux >= 4.0: ``5`` written to ``clear_refs``).

    Returns:
        Whether it was reset (False elsewhere: the peak then stays the process's since it started).
    """
    try:
        clear_refs.write_text("5")
    except OSError:
        return False
    return True


def peak_rss_mb(status: Path = Path("/proc/self/status")) -> float:
    """Return this process's peak resident set size in MiB.

    Linux: ``VmHWM`` of ``status`` (the high-water mark of the process's own memory). Not
    ``ru_maxrss``: that one is kept across ``fork`` and ``execve``, so a process started by a
    large one (a benchmark that has joined a dataset, then starts the joiner) reports at least its
    parent's size (measured: a fresh interpreter started by a 400 MB process, 407 MB against a
    VmHWM of 11 MB). Elsewhere ``ru_maxrss`` (KiB on Linux, bytes on macOS: read as KiB).
    """
    try:
        for line in status.read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024.0  # kB
    except (OSError, ValueError, IndexError):
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
