"""The offline command line: outputs, report, error exit code."""

from __future__ import annotations

import json

import pytest

from linear_slam_ros.cli.main import main
from support import CACHE, dataset_archive, read_rows

REPORT_KEYS = {
    "method", "n_submaps", "state_dim", "seconds", "per_submap_ms_p50", "per_submap_ms_p99",
    "per_submap_ms_max", "peak_rss_mb", "chi2", "info_nnz",
}


@pytest.fixture(autouse=True)
def _cache(monkeypatch):
    monkeypatch.setenv("LINEAR_SLAM_CACHE", str(CACHE))


@pytest.mark.parametrize("method", ["sequential", "dc", "online-dc"])
def test_join_writes_reference_format_and_report(method, tmp_path):
    out = tmp_path / method
    assert main(["join", str(dataset_archive("8240_data_50_local_maps")), "--method", method, "--out", str(out)]) == 0
    report = json.loads((out / "report.json").read_text())
    assert set(report) >= REPORT_KEYS
    assert report["method"] == method and report["n_submaps"] == 50
    poses = read_rows(out / "poses.txt")
    assert sorted(poses)[:3] == [0, 1, 2] and len(poses[1]) == 3
    assert list(poses[0]) == [0.0, 0.0, 0.0]
    assert len(read_rows(out / "features.txt")) > 100
    expected = {"sequential": 1399.6, "dc": 528.7, "online-dc": 528.7}[method]
    assert report["chi2"] == pytest.approx(expected, rel=0.01)


def test_refine_and_pose_only_kind(tmp_path):
    assert main(["refine", str(dataset_archive("Intel")), "--out", str(tmp_path)]) == 0
    report = json.loads((tmp_path / "report.json").read_text())
    assert report["kind"] == "2DPG" and report["chi2"] == pytest.approx(546.46, rel=0.005)
    assert report["linear_chi2"] == pytest.approx(546.51, rel=0.005)
    assert not (tmp_path / "features.txt").exists()


def test_bad_dataset_exits_2_with_a_message(tmp_path, caplog):
    assert main(["join", str(tmp_path / "missing"), "--out", str(tmp_path / "o")]) == 2
    assert "neither a folder nor a .tar.xz archive" in caplog.text


@pytest.mark.parametrize(("method", "map_type"), [("online-dc", "as-is"), ("sequential", "as-is"), ("online-dc", "feature-only")])
def test_save_state_then_initial_state_equals_one_run(method, map_type, tmp_path):
    import numpy as np

    from linear_slam_ros.evaluation.synthetic import make_world, noisy_local_maps
    from linear_slam_ros.io.datasets import MapKind
    from support import write_dataset

    world = make_world(2, 36, 40, np.random.default_rng(3))
    maps = noisy_local_maps(world, np.random.default_rng(4), steps_per_map=3, sensor_range=7.0)
    for name, part in (("all", maps), ("first", maps[:5]), ("rest", maps[5:])):
        write_dataset(part, tmp_path / name, MapKind.PF2D)
    common = ["--method", method, "--map-type", map_type]
    assert main(["join", str(tmp_path / "all"), *common, "--out", str(tmp_path / "o_all")]) == 0
    state = tmp_path / "first.npz"
    assert main(["join", str(tmp_path / "first"), *common, "--out", str(tmp_path / "o1"), "--save-state", str(state)]) == 0
    assert main(["join", str(tmp_path / "rest"), *common, "--out", str(tmp_path / "o2"), "--initial-state", str(state)]) == 0
    for result in ("features.txt", "poses.txt") if map_type == "as-is" else ("features.txt",):
        one_run, continued = read_rows(tmp_path / "o_all" / result), read_rows(tmp_path / "o2" / result)
        assert set(one_run) == set(continued), result
        for k in one_run:
            np.testing.assert_allclose(continued[k], one_run[k], rtol=0, atol=1e-9, err_msg=f"{result} {k}")


def test_initial_state_of_another_method_exits_2(tmp_path, caplog):
    state = tmp_path / "s.npz"
    archive = str(dataset_archive("8240_data_50_local_maps"))
    assert main(["join", archive, "--method", "sequential", "--out", str(tmp_path / "a"), "--save-state", str(state)]) == 0
    assert main(["join", archive, "--method", "online-dc", "--out", str(tmp_path / "b"), "--initial-state", str(state)]) == 2
    assert "the saved map was joined with mode='sequential'" in caplog.text
