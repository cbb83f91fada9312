"""The authors' C++ Linear SLAM program as a timing anchor, run beside the project when present.

The program is not part of the project and is never shipped: the benchmark looks for it next to
the datasets folder (``DATASETS/../reference/LinearSLAM``, e.g. ``../shared/reference/``), and
compares only when it is there. It prints ``Used Time: <s> sec`` last, the CPU time of its
joining (file reading excluded): the benchmark sets it beside the CPU time of the project's
joining on one BLAS thread (on an idle host both equal their wall times).
"""

from __future__ import annotations

import os
import re
import subprocess
import tempfile
from dataclasses import dataclass
from pathlib import Path

from linear_slam_ros.core.cholmod import OPENMP_THREAD_LIMIT

PROGRAM_NAME = "LinearSLAM"
"""File name of the program, in the ``reference`` folder beside the datasets folder."""

PROGRAM_METHODS = {"dc": "DC", "sequential": "SEQ"}
"""The program's ``-meth`` value of each project method it also has."""

_USED_TIME = re.compile(r"Used Time:\s*([0-9]+(?:\.[0-9]*)?(?:[eE][-+]?[0-9]+)?)")


@dataclass(frozen=True)
class ProgramRun:
    """One run of the reference program.

    Attributes:
        method: the project's name of the method (``"dc"`` or ``"sequential"``).
        seconds: its ``Used Time`` (s), or ``None`` when it failed or timed out.
        error: why there is no time (``None`` when there is one).
    """

    method: str
    seconds: float | None
    error: str | None = None


def find_program(datasets_dir: Path) -> Path | None:
    """Return the program beside ``datasets_dir`` (``../reference/LinearSLAM``) if it is an executable file."""
    candidate = datasets_dir.resolve().parent / "reference" / PROGRAM_NAME
    return candidate if candidate.is_file() and os.access(candidate, os.X_OK) else None


def parse_used_time(output: str) -> float | None:
    """Return the last ``Used Time: <s> sec`` figure of the program's output (s), or ``None``."""
    found = _USED_TIME.findall(output)
    return float(found[-1]) if found else None


def run_program(
    program: Path, dataset_dir: Path, n_maps: int, kind: str, method: str, timeout_s: float = 900.0
) -> ProgramRun:
    """Run the program on a folder of local maps with one BLAS thread; return its ``Used Time``.

    OpenMP is limited as the project's CHOLMOD is (:data:`~linear_slam_ros.core.cholmod.OPENMP_THREAD_LIMIT`,
    unless the environment sets ``OMP_THREAD_LIMIT``): both link the same ``libcholmod``, whose
    supernodal loops would otherwise run on 4 threads, all counted in the program's ``Used Time``.

    Args:
        program: the executable.
        dataset_dir: folder of ``localmap_<i>.txt``.
        n_maps: how many local maps to join (``-num``).
        kind: the datasets' map kind, ``2DPF``, ``3DPF``, ``2DPG`` or ``3DPG`` (``-type``).
        method: ``"dc"`` or ``"sequential"``.
        timeout_s: wall-time limit (s); a run past it is reported as timed out.

    Raises:
        ValueError: ``method`` is not one the program has.
    """
    if method not in PROGRAM_METHODS:
        raise ValueError(f"the reference program has no method {method!r} (it has {sorted(PROGRAM_METHODS)})")
    # one BLAS thread, and OpenMP's limit as the project's CHOLMOD has it (the same libcholmod: core/cholmod.py)
    env = {"OMP_THREAD_LIMIT": OPENMP_THREAD_LIMIT, **os.environ, "OPENBLAS_NUM_THREADS": "1"}
    with tempfile.TemporaryDirectory(prefix="linear_slam_reference_") as tmp:
        out = Path(tmp)
        cmd = [
            str(program), "-path", f"{dataset_dir}/", "-num", str(n_maps), "-meth", PROGRAM_METHODS[method],
            "-type", kind, "-p", str(out / "poses.txt"), "-f", str(out / "features.txt"),
        ]  # fmt: skip
        try:
            done = subprocess.run(cmd, capture_output=True, text=True, env=env, cwd=tmp, timeout=timeout_s, check=False)
        except subprocess.TimeoutExpired:
            return ProgramRun(method, None, f"timed out after {timeout_s:.0f} s")
        except OSError as exc:
            return ProgramRun(method, None, f"could not run: {exc}")
    seconds = parse_used_time(done.stdout)
    if seconds is None:
        tail = (done.stdout + done.stderr).strip().splitlines()[-1:] or ["no output"]
        return ProgramRun(method, None, f"exit {done.returncode}, no 'Used Time' ({tail[0][:120]})")
    return ProgramRun(method, seconds)
