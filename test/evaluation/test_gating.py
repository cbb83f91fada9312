"""The gating benchmark's trial draw (evaluation/gating.py): what can be corrupted, and when nothing can."""

from __future__ import annotations

import numpy as np

from linear_slam_ros.core.local_map import POSE, LocalMap
from linear_slam_ros.evaluation.gating import any_corruptible, clean_pass, closures_tested, corruptible
from linear_slam_ros.evaluation.synthetic import make_world, noisy_local_maps


def _forward_star(k: int) -> LocalMap:
    """Star chunk from pose k: odometry to k + 1 (its end pose) and a loop closure forward to k + 3 (sphere2500's shape)."""
    x = np.array([1.0, 0.0, 0.0, 3.0, 0.0, 0.0])
    return LocalMap(2, k, k + 1, np.array([k + 1, k + 3]), np.array([POSE, POSE], dtype=np.int8), x, 100.0 * np.eye(6))


def test_without_holding_a_stream_whose_only_shared_variables_are_end_poses_has_nothing_to_corrupt():
    maps = [_forward_star(k) for k in range(8)]
    clean = clean_pass(maps, hold=False)
    assert max(clean.dof) > 0  # the gate tests the end poses the loop closures brought in
    assert not any_corruptible(maps, clean)  # ... but a trial never moves an end pose: no draw can succeed
    assert clean.closure_results == []


def test_held_forward_closures_are_tested_when_the_chain_reaches_them_and_can_be_corrupted():
    maps = [_forward_star(k) for k in range(8)]
    clean = clean_pass(maps)
    assert max(clean.dof) == 0  # the end poses now come in through the chain: nothing of a submap is shared
    tested = [(c.seq, c.origin, c.target, j + 1, r.dof) for j, c, r, _ in clean.closure_results]
    # submap k (seq k + 1) closes k -> k + 3; the chain reaches pose k + 3 with submap k + 2 (seq k + 3)
    assert tested == [(k + 1, k, k + 3, k + 3, 3) for k in range(6)]
    closures = closures_tested(clean)
    assert closures == {k: {k + 3: k + 2} for k in range(6)}
    assert any_corruptible(maps, clean)
    assert corruptible(2, maps, clean, closures) == [1]  # the closure's pose, never the end pose
    assert np.array_equal(clean.final.x, clean.plain_final.x)  # nothing gated: the ungated map (closures held), bit for bit


def test_a_stream_with_revisited_features_has_something_to_corrupt():
    world = make_world(2, 24, 20, np.random.default_rng(11))
    maps = noisy_local_maps(world, np.random.default_rng(12), steps_per_map=3)
    assert any_corruptible(maps, clean_pass(maps))


def test_run_dataset_without_holding_gives_such_a_stream_the_clean_check_only(monkeypatch, tmp_path, caplog):
    import linear_slam_ros.evaluation.gating as gating

    maps = [_forward_star(k) for k in range(8)]
    monkeypatch.setattr(gating, "_load", lambda name, datasets_dir: maps)
    out = gating.run_dataset("forward-stars", tmp_path, trials=5, seed=1, probability=gating.PROBABILITY, hold=False)
    assert out["trials"] == 0 and "end pose" in out["trials_skipped"]
    assert out["clean_gated"] == 0 and out["n_submaps"] == 8 and "detected" not in out
    assert "no corruption trial can be drawn" in caplog.text


def test_a_corrupted_held_closure_is_detected_when_the_chain_reaches_it_and_costs_the_map_nothing(monkeypatch, tmp_path):
    import linear_slam_ros.evaluation.gating as gating

    rng = np.random.default_rng(5)
    maps = []
    for k in range(40):  # consistent noisy stars: the closure k -> k + 3 agrees with three odometry steps
        x = np.array([1.0, 0.0, 0.0, 3.0, 0.0, 0.0]) + rng.normal(scale=0.01, size=6)
        n = 2 if k + 3 <= 40 else 1  # the last ones close on no pose the chain reaches: odometry alone
        maps.append(LocalMap(2, k, k + 1, np.array([k + 1, k + 3])[:n], np.full(n, POSE, dtype=np.int8), x[:3 * n],
                             1e4 * np.eye(3 * n)))
    monkeypatch.setattr(gating, "_load", lambda name, datasets_dir: maps)
    out = gating.run_dataset("noisy-stars", tmp_path, trials=4, seed=3, probability=gating.PROBABILITY)
    assert out["clean_gated"] == 0 and out["n_closures_tested"] == 38
    assert out["held_closure_trials"] == 4 and out["detected"] == 4  # every trial moves a closure by 1-3 m: far out
    assert all(r["held_closure_tested_at"] == r["submap"] + 2 for r in out["rows"])
    assert out["rms_max_m"] == 0.0  # split off exactly: the same state as the clean run without it
    assert any(r["rerun"] for r in out["rows"])  # ... which one re-run to the end confirms
