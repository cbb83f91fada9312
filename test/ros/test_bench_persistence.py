"""The persistence benchmark's figures: which seconds make the cost, and the verdicts it writes."""

from __future__ import annotations

import pytest

from linear_slam_ros.ros.bench_persistence import dataset_figures, markdown, run_figures


def _phases(journal_s, snapshot_s, snapshot_cpu_s, join_s=5.0, restore_s=0.2):
    baseline = {"join_seconds_total": join_s, "stop_s": 0.4, "end_to_end_s": 40.0}
    persisted = {
        "join_seconds_total": join_s, "journal_seconds_total": journal_s, "snapshot_seconds_total": snapshot_s,
        "journal_cpu_seconds_total": journal_s / 2, "snapshot_cpu_seconds_total": snapshot_cpu_s,
        "join_cpu_seconds_total": join_s / 2, "stop_s": 0.6, "end_to_end_s": 41.0, "state_dir_bytes": 32e6,
    }
    restored = {"restore_seconds_total": restore_s, "resumed_log_s": restore_s, "start_to_map_s": 3.0}
    return baseline, persisted, restored


def test_the_cost_is_the_journal_wall_time_and_the_snapshots_cpu_time():
    run = run_figures(1, *_phases(journal_s=0.3, snapshot_s=0.5, snapshot_cpu_s=0.15))
    assert run["cost_ratio"] == pytest.approx((0.3 + 0.15) / 5.0)
    assert run["ratio"] == pytest.approx((0.3 + 0.5) / 5.0)  # wall only: the snapshots' fsync waits too
    assert run["cpu_ratio"] == pytest.approx((0.15 + 0.15) / 2.5)
    assert run["ab_ratio"] == pytest.approx(5.3 / 5.0)


def test_the_verdicts_follow_the_cost_and_say_the_wall_figure_too():
    cheap = run_figures(1, *_phases(journal_s=0.3, snapshot_s=0.5, snapshot_cpu_s=0.15))
    dear = run_figures(2, *_phases(journal_s=0.3, snapshot_s=0.5, snapshot_cpu_s=0.25, restore_s=2.5))
    met = dataset_figures("VicPark_6898_local_maps", 6898, [cheap])
    missed = dataset_figures("VicPark_6898_local_maps", 6898, [cheap, dear])
    assert met["ratio_met"] and not met["wall_ratio_met"] and met["restore_met"]
    assert not missed["ratio_met"] and not missed["restore_met"]
    text = markdown([met], "cmd")
    assert "cost (journal s + snapshot CPU s) / join 0.090 (target <= 0.10): met; in wall time only 0.160 (NOT within" in text
    assert "| (0.300 + 0.150) / 5.00 = **0.090** | 0.160 |" in text
    assert "restore 0.20 s (target <= 2.0 s): met" in text
    text = markdown([missed, {"dataset": "manhattanOlson3500", "skipped": "not found"}], "cmd")
    assert "0.090, 0.110 (target <= 0.10): NOT met" in text and "restore 0.20, 2.50 s (target <= 2.0 s): NOT met" in text
    assert "- manhattanOlson3500: skipped (not found)" in text
    assert "a cross-check, not the target's figure: the join seconds without state alone range 5.00-5.00 s (±0%" in text
