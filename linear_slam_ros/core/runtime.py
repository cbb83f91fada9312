"""Process-level tuning for the joiners, applied by the programs (CLI, node), never on import.

Two settings were measured to matter on the 2-core target machine (docs/scale.md and docs/results.md):

* BLAS threads. numpy and scipy each bundle an OpenBLAS; both start a thread per core and
  oversubscribe the two cores. The exact sequential joiner, a string of rank-``c`` updates of a
  dense matrix, runs twice as fast with one BLAS thread (VicPark200: 2.2 s -> 1.1 s). The node
  runs every mode on one (:data:`SHARED_MACHINE_BLAS_THREADS`): a spinning helper holds a core.
* glibc's dynamic mmap threshold. Each sequential step allocates a slightly larger matrix than
  the last; glibc then serves every one with a fresh ``mmap`` and pays page faults on all of
  it. A fixed, high threshold lets freed matrices be reused (VicPark200: 1.1 s -> 0.85 s).
  Fixing it also fixes glibc's trim threshold at its default, 128 KiB, so a freed matrix at the
  top of the heap was still handed back and faulted in again by the next step; with the
  reusing threshold the trim threshold is raised to match (exact sequential, VicPark200 and
  DLR200: the copy of the covariance into each step's new matrix 0.27 -> 0.10 s and 0.44 ->
  0.21 s). With the returning one it stays at the default: a 4 MiB trim threshold raised the
  node's peak RSS on manhattanOlson3500 from 220-224 to 238-245 MB (two runs each).
  The other strategies allocate and free large sparse arrays from several threads in the node,
  where a high threshold keeps freed blocks in each thread's heap: a fixed 4 MiB threshold hands
  them back (node peak RSS, two runs each: features2d-5000 513-515 MB against 731-859 MB,
  manhattanOlson3500 243-255 against 250-275 MB; the node's join seconds on features2d-5000
  4.38-5.59 against 4.02-4.16, perhaps slower, within this machine's noise; offline join times unchanged).
"""

from __future__ import annotations

import ctypes
import ctypes.util
import logging
import sys
from contextlib import AbstractContextManager, nullcontext

logger = logging.getLogger(__name__)

_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3
MMAP_THRESHOLD_REUSE = 1 << 30
"""Bytes: glibc's mmap threshold for the exact sequential strategies (freed dense matrices reused)."""
MMAP_THRESHOLD_RETURN = 4 << 20
"""Bytes: glibc's mmap threshold for the other strategies (large freed arrays handed back)."""
DEFAULT_TRIM_THRESHOLD = 128 << 10
"""Bytes: glibc's default trim threshold (free memory at the heap's top beyond it is handed back)."""


def tune_allocator(threshold_bytes: int) -> bool:
    """Fix glibc's mmap and trim thresholds (no dynamic thresholds); return success.

    Args:
        threshold_bytes: allocations of at least this many bytes are mapped, and unmapped when
            freed; smaller ones come from the heap (a strategy's ``mmap_threshold``). From
            :data:`MMAP_THRESHOLD_REUSE` up, free memory at the heap's top is kept up to this
            many bytes too (trim threshold); below, it is handed back beyond
            :data:`DEFAULT_TRIM_THRESHOLD`, glibc's default.

    A no-op returning ``False`` on platforms without glibc's ``mallopt``.
    """
    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        trim_bytes = threshold_bytes if threshold_bytes >= MMAP_THRESHOLD_REUSE else DEFAULT_TRIM_THRESHOLD
        ok = bool(libc.mallopt(_M_MMAP_THRESHOLD, threshold_bytes))
        ok = bool(libc.mallopt(_M_TRIM_THRESHOLD, trim_bytes)) and ok
    except (OSError, AttributeError):
        return False
    logger.debug("mallopt(M_MMAP_THRESHOLD, %d), mallopt(M_TRIM_THRESHOLD, %d) -> %s", threshold_bytes, trim_bytes, ok)
    return ok


SHARED_MACHINE_BLAS_THREADS = 1
"""BLAS threads of a process that runs beside other work (the node in every mode, the race's joiner as
the node's, the refiner process). numpy's and scipy's OpenBLAS start a thread per core, and after each call a helper keeps
spinning for the next one; a stream's joins and outputs call every few milliseconds, so it never sleeps
and holds a core that the node's own threads (arrivals, outputs, background merges), the refiner and
the front-end need. sphere2500 through the node (``demo``, three runs alternated, docs/scale.md, "One thread
for BLAS and for CHOLMOD's OpenMP"): the joiner's CPU 20.9, 18.5, 16.3 s with a thread per core
against 12.9, 12.7, 14.1 s with one. Offline and alone on the machine, a second thread shortens some
runs (``run_join`` keeps each strategy's own ``blas_threads``)."""


def blas_threads(n_threads: int | None) -> AbstractContextManager[object]:
    """Return a context that limits BLAS threads to ``n_threads`` (``None``: leave as is)."""
    if n_threads is None:
        return nullcontext()
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:  # pragma: no cover - threadpoolctl is a pinned dependency
        return nullcontext()
    return threadpool_limits(limits=n_threads, user_api="blas")


def set_blas_threads(n_threads: int | None) -> None:
    """Limit BLAS threads for the rest of the process (``None``: leave as is); for long-lived
    programs such as the node."""
    if n_threads is None:
        return
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:  # pragma: no cover - threadpoolctl is a pinned dependency
        return
    threadpool_limits(limits=n_threads, user_api="blas")  # applies on construction


def release_memory() -> bool:
    """Hand freed heap memory back to the system (glibc ``malloc_trim``); return whether it ran.

    Below the mmap threshold of :func:`tune_allocator` (1 GiB for sequential joining), freed arrays
    stay in the heap for reuse; after a reset nothing will reuse them soon, so the node trims the heap.
    """
    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        return bool(libc.malloc_trim(0))
    except (OSError, AttributeError):
        return False
