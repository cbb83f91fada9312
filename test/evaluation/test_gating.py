"""The gating benchmark's trial draw (evaluation/gating.py): what can be corrupted, and when nothing can."""

from __future__ import annotations

import numpy as np

from linear_slam_ros.core.local_map import POSE, LocalMap
from linear_slam_ros.evaluation.gating import any_corruptible, clean_pass
from linear_slam_ros.evaluation.synthetic import make_world, noisy_local_maps


def _forward_star(k: int) -> LocalMap:
    """Star chunk from pose k: odometry to k + 1 (its end pose) and a loop closure forward to k + 3 (sphere2500's shape)."""
    x = np.array([1.0, 0.0, 0.0, 3.0, 0.0, 0.0])
    return LocalMap(2, k, k + 1, np.array([k + 1, k + 3]), np.array([POSE, POSE], dtype=np.int8), x, 100.0 * np.eye(6))


def test_a_stream_whose_only_shared_variables_are_end_poses_has_nothing_to_corrupt():
    maps = [_forward_star(k) for k in range(8)]
    clean = clean_pass(maps)
    assert max(clean.dof) > 0  # the gate tests the end poses the loop closures brought in
    assert not any_corruptible(maps, clean)  # ... but a trial never moves an end pose: no draw can succeed


def test_a_stream_with_revisited_features_has_something_to_corrupt():
    world = make_world(2, 24, 20, np.random.default_rng(11))
    maps = noisy_local_maps(world, np.random.default_rng(12), steps_per_map=3)
    assert any_corruptible(maps, clean_pass(maps))


def test_run_dataset_gives_such_a_stream_the_clean_check_only(monkeypatch, tmp_path, caplog):
    import linear_slam_ros.evaluation.gating as gating

    maps = [_forward_star(k) for k in range(8)]
    monkeypatch.setattr(gating, "_load", lambda name, datasets_dir: maps)
    out = gating.run_dataset("forward-stars", tmp_path, trials=5, seed=1, probability=gating.PROBABILITY)
    assert out["trials"] == 0 and "end pose" in out["trials_skipped"]
    assert out["clean_gated"] == 0 and out["n_submaps"] == 8 and "detected" not in out
    assert "no corruption trial can be drawn" in caplog.text
