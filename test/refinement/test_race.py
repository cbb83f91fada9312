"""The race's CPU accounting and its table (``linear_slam_ros.refinement.race``); iSAM2 is not run here."""

from __future__ import annotations

import math
import time

import pytest

from linear_slam_ros.refinement import race


def _busy(seconds: float) -> None:
    end = time.thread_time() + seconds
    while time.thread_time() < end:
        pass


def test_run_ours_splits_the_cpu_of_joining_outputs_and_refiner(read_benchmark, monkeypatch):
    maps = read_benchmark("Intel").maps[:600]
    linear_map = race._linear_map

    def slow_output(state):  # outputs that overlap the joins for certain: 0.1 s of CPU each
        _busy(0.1)
        return linear_map(state)

    monkeypatch.setattr(race, "_linear_map", slow_output)
    ours = race.run_ours(maps)
    assert ours["n_submaps"] == 600
    assert ours["cpu_outputs_s"] >= 0.2  # the final output and at least one during the joins
    assert ours["cpu_join_s"] > 0 and ours["cpu_outputs_s"] > 0 and ours["cpu_refiner_s"] > 0
    # each thread's own CPU: the joins and the outputs are parts of the process's
    assert ours["cpu_join_s"] + ours["cpu_outputs_s"] <= ours["cpu_parent_s"] + 1e-3
    assert ours["cpu_rest_s"] == pytest.approx(ours["cpu_parent_s"] - ours["cpu_join_s"] - ours["cpu_outputs_s"])
    assert ours["cpu_join_refine_s"] == pytest.approx(ours["cpu_total_s"] - ours["cpu_outputs_s"])
    assert ours["publications_after_last"] and not math.isnan(ours["chi2_linear"])
    assert ours["worker_exitcodes"] == [0]  # the refiner stopped cleanly


def _entry(join_refine: float, total: float, isam_cpu: float | None, queries: float = 0.0) -> dict:
    ours = {
        "n_submaps": 10, "join_p50_ms": 0.2, "join_p99_ms": 1.0, "join_max_ms": 2.0, "cpu_join_s": 0.4,
        "cpu_rest_s": 0.1, "cpu_refiner_s": join_refine - 0.5, "cpu_join_refine_s": join_refine,
        "cpu_outputs_s": total - join_refine, "cpu_total_s": total, "chi2_linear": 12.0, "chi2_refined": 10.0,
        "refined_lag_s": 0.5,
    }
    isam = None if isam_cpu is None else {
        "update_p50_ms": 1.0, "update_p99_ms": 3.0, "update_max_ms": 5.0, "cpu_total_s": isam_cpu, "chi2": 10.0,
        "cpu_estimate_queries_s": queries,
    }
    checks = {
        "refined_lag": True,
        "cpu_third_of_isam2": race._within_third(join_refine, isam),
        "cpu_third_of_isam2_with_outputs": race._within_third(total, isam),
        "cpu_third_of_isam2_updates": race._within_third(join_refine, isam, updates_only=True),
    }
    return {"stream": "s", "ours": ours, "isam2": isam, "optimum_chi2": 10.0, "checks": checks}


def test_the_table_shows_both_ratios_and_names_each_missed_check():
    table = race.to_markdown([_entry(join_refine=1.0, total=2.0, isam_cpu=4.0)])
    assert "0.40 + 0.10 + 0.50 = 1.00 (+ 1.00 = 2.00)" in table
    assert "| 4.00 (queries 0.00) | 10.00 | 0.25 (0.50) | 0.25 |" in table
    assert "Targets missed: s: cpu_third_of_isam2_with_outputs" in table
    assert "Targets missed: none" in race.to_markdown([_entry(join_refine=1.0, total=1.2, isam_cpu=4.0)])
    both = race.to_markdown([_entry(join_refine=2.0, total=3.0, isam_cpu=4.0)])
    assert "s: cpu_third_of_isam2, s: cpu_third_of_isam2_with_outputs, s: cpu_third_of_isam2_updates" in both


def test_the_estimate_queries_that_start_new_poses_are_reported_apart():
    """``calculateEstimate(key)`` for each new pose's start makes iSAM2 back-substitute at every update: 20-50% of its
    CPU on the larger streams (review of session 26); the ratio to its updates alone is reported and checked too."""
    entry = _entry(join_refine=1.2, total=1.5, isam_cpu=4.0, queries=1.0)
    assert entry["checks"] == {"refined_lag": True, "cpu_third_of_isam2": True, "cpu_third_of_isam2_with_outputs": False,
                               "cpu_third_of_isam2_updates": False}
    table = race.to_markdown([entry])
    assert "| 4.00 (queries 1.00) | 10.00 | 0.30 (0.38) | 0.40 |" in table
    assert "s: cpu_third_of_isam2_with_outputs, s: cpu_third_of_isam2_updates" in table


def test_a_race_of_no_stream_fails_and_writes_nothing(tmp_path, capsys):
    """``--only intel`` (the archive is ``Intel``) wrote an empty table that said "Targets missed: none" and exited 0."""
    out = tmp_path / "out"
    assert race.main(["--datasets-dir", str(tmp_path), "--out", str(out), "--only", "intel"]) == 2
    assert "race: no archive " + str(tmp_path / "intel.tar.xz") in capsys.readouterr().err
    assert not out.exists()
    assert race.main(["--datasets-dir", str(tmp_path / "none"), "--out", str(out)]) == 2  # the default streams'
    assert "Intel.tar.xz" in capsys.readouterr().err and not out.exists()


def test_no_isam2_run_checks_nothing_against_it():
    assert race._within_third(1.0, None) is None
    table = race.to_markdown([_entry(join_refine=1.0, total=2.0, isam_cpu=None)])
    assert "– | – | – | – | –" in table and "Targets missed: none" in table
