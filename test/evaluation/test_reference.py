"""The reference-program comparison of the benchmark: found only when present, its time parsed, the table."""

from __future__ import annotations

from linear_slam_ros.evaluation.benchmark import _program_table
from linear_slam_ros.evaluation.reference import find_program, parse_used_time, run_program


def test_parse_used_time_takes_the_last_figure():
    out = "Reading...\nUsed Time: 1.5 sec\nJoin...\nUsed Time: 2.58 sec\n"
    assert parse_used_time(out) == 2.58
    assert parse_used_time("Used Time: 3e-2 sec") == 0.03
    assert parse_used_time("no time here") is None


def test_find_program_only_when_an_executable_is_beside_the_datasets(tmp_path):
    datasets = tmp_path / "datasets"
    datasets.mkdir()
    assert find_program(datasets) is None
    program = tmp_path / "reference" / "LinearSLAM"
    program.parent.mkdir()
    program.write_text("#!/bin/sh\n")
    assert find_program(datasets) is None  # not executable
    program.chmod(0o755)
    assert find_program(datasets) == program.resolve()


def test_run_program_passes_one_blas_thread_and_reads_used_time(tmp_path, monkeypatch):
    program = tmp_path / "LinearSLAM"
    program.write_text('#!/bin/sh\necho "args: $*"\necho "Used Time: ${OPENBLAS_NUM_THREADS}.${OMP_THREAD_LIMIT}5 sec"\n')
    program.chmod(0o755)
    monkeypatch.delenv("OMP_THREAD_LIMIT", raising=False)
    run = run_program(program, tmp_path, 3, "2DPF", "dc")
    assert run.seconds == 1.15 and run.error is None  # one BLAS thread, OpenMP limited as the project's CHOLMOD
    monkeypatch.setenv("OMP_THREAD_LIMIT", "3")
    assert run_program(program, tmp_path, 3, "2DPF", "dc").seconds == 1.35  # a limit the user set holds for both
    program.write_text("#!/bin/sh\necho oops\nexit 3\n")
    failed = run_program(program, tmp_path, 3, "2DPF", "sequential")
    assert failed.seconds is None and "exit 3" in (failed.error or "")


def test_table_says_when_the_program_is_absent_and_gives_ratios_when_present():
    absent = [{"dataset": "d", "reference_program": {"path": None, "looked_for": "/x/reference/LinearSLAM"}}]
    text = "\n".join(_program_table(absent))
    assert "absent" in text and "/x/reference/LinearSLAM" in text
    run = {"project_seconds": 1.0, "program_seconds": 2.0, "ratio": 0.5, "target_ratio": 1.0, "repeats": 3,
           "program_error": None}
    present = [{"dataset": "d", "reference_program": {"path": "/p", "runs": {"dc": run}}}]
    text = "\n".join(_program_table(present))
    assert "| d | dc | 1.000 | 2.000 | 3 | 0.500 | 1.00 | yes |" in text


def test_the_project_is_timed_by_cpu_beside_the_program_s_cpu_time(tmp_path, monkeypatch):
    """The program's ``Used Time`` is CPU time; the project's wall time beside it swung the ratio from about 1 to 9
    on a loaded host (a review of session 26)."""
    import time

    import numpy as np

    from linear_slam_ros.evaluation import benchmark
    from linear_slam_ros.evaluation.reference import ProgramRun
    from linear_slam_ros.evaluation.runner import JoinRun, run_join
    from linear_slam_ros.evaluation.synthetic import make_world, noisy_local_maps
    from linear_slam_ros.joiner.strategy import JoinMethod

    maps = noisy_local_maps(make_world(2, 24, 20, np.random.default_rng(3)), np.random.default_rng(4), steps_per_map=3)
    real = run_join(maps, "dc")
    assert 0.0 < real.cpu_seconds < 10.0 * real.seconds + 0.05  # measured over the same span
    slow = run_join(maps, "dc", progress=lambda _: time.sleep(0.1))  # waiting (a level each): wall grows, CPU does not
    assert slow.seconds > slow.cpu_seconds + 0.2

    monkeypatch.setattr(benchmark, "run_join", lambda m, method: JoinRun(JoinMethod.DC, None, 5.0, (), 1, "x", 1.0))
    monkeypatch.setattr(benchmark, "run_program", lambda *args: ProgramRun("dc", 2.0))
    monkeypatch.setattr(benchmark, "list_local_map_files", lambda folder: [folder])

    class _Dataset:
        maps = ()
        kind = JoinMethod.DC  # anything with a .value
        name = "d"

    out = benchmark.compare_with_program(_Dataset(), tmp_path, tmp_path / "LinearSLAM", ["dc"], 10)
    assert out["dc"]["project_seconds"] == 1.0 and out["dc"]["ratio"] == 0.5
    assert out["dc"]["project_wall_all"] == [5.0] * out["dc"]["repeats"]
