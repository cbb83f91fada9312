"""The main job's report: the node's default mode, freshness, throughput and memory, next to the join figures."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

from linear_slam_ros.joiner.config import JoinerConfig
from linear_slam_ros.ros.bench_node import _checks, to_markdown
from support import REPO

FRESHNESS = [f"freshness_{w}_ms_{q}" for w in ("pose", "map") for q in ("p50", "p99", "max")]


def test_demo_reports_freshness_throughput_and_memory_in_the_default_mode(tmp_path):
    """A 24-submap synthetic stream through the installed joiner with no --mode: every new report key is filled in."""
    out = tmp_path / "out"
    cmd = [sys.executable, "-m", "linear_slam_ros.ros.demo", "--dataset", "synthetic:features2d-24@3",
           "--bag", str(tmp_path / "bag"), "--out", str(out)]
    done = subprocess.run(cmd, cwd=REPO, env=dict(os.environ), capture_output=True, text=True, timeout=180)
    assert done.returncode == 0, done.stdout[-2000:] + done.stderr[-2000:]
    report = json.loads((out / "report.json").read_text())
    assert report["mode"] == JoinerConfig().mode.value == "online-dc"
    assert report["n_submaps_joined"] == report["n_submaps_sent"] == 24
    for key in FRESHNESS:
        assert isinstance(report[key], float) and report[key] >= 0.0, key
    assert report["freshness_pose_ms_p50"] <= report["freshness_pose_ms_max"]
    assert report["freshness_pose_ms_max"] <= report["freshness_map_ms_max"]  # the pose goes out first
    assert report["submaps_per_second"] > 0 and report["joiner_peak_rss_mb"] > 50.0
    assert 0.1 < report["joiner_cpu_s"] < 600.0  # the process's CPU, start-up (imports) included
    assert 0.0 < report["replay_cpu_s"] < 600.0
    assert report["joiner_exit_code"] == 0


def test_benchmark_checks_name_every_missed_target():
    entry = {
        "dataset": "city", "mode": "online-dc", "n_submaps_sent": 20000, "n_submaps_joined": 20000, "pose_only": True,
        "per_submap_ms_p50": 0.3, "per_submap_ms_p99": 12.0, "per_submap_ms_max": 80.0,
        "freshness_pose_ms_p50": 5.0, "freshness_pose_ms_p99": 20.0, "freshness_pose_ms_max": 60.0,
        "freshness_map_ms_p50": 900.0, "freshness_map_ms_p99": 2500.0, "freshness_map_ms_max": 3000.0,
        "submaps_per_second": 450.0, "joiner_peak_rss_mb": 400.0, "rss_bound_mb": 500.0, "map_difference": 0.0,
        "chi2": 1.0, "offline_chi2": 1.0,
    }
    checks = _checks(entry)
    assert [k for k, ok in checks.items() if ok is False] == ["join_p99", "map_fresh_p99", "throughput"]
    assert checks["rss"] and checks["map_equal"] and checks["join_max"]
    table = to_markdown([{**entry, "checks": checks}])
    assert "Targets missed: city: join_p99, city: map_fresh_p99, city: throughput" in table
    small = _checks({**entry, "n_submaps_sent": 500, "n_submaps_joined": 500})
    assert small["map_fresh_p99"] is None and small["throughput"] is None  # targets of the 10,000/20,000 scale only


def test_sim_demo_refuses_bad_sizes_before_starting_anything(tmp_path, capsys):
    from linear_slam_ros.core.errors import ConfigError
    from linear_slam_ros.ros.demo import main, run_sim_demo

    assert main(["--sim", "--n-maps", "0", "--out", str(tmp_path)]) == 2
    assert "--n-maps 0 must be at least 1 and --sim-rate 20.0 positive" in capsys.readouterr().err
    with pytest.raises(ConfigError, match=r"--sim-rate -1\.0 positive"):
        run_sim_demo(tmp_path, n_maps=5, rate=-1.0)
    assert not any(tmp_path.iterdir())  # nothing written


def test_the_demo_finds_its_default_bag_outside_a_checkout_and_refuses_a_missing_one(tmp_path, monkeypatch, capsys):
    """`ros2 run linear_slam_ros demo` from any folder replays the bag installed with the package."""
    from linear_slam_ros.ros.demo import DEFAULT_DATASET, default_bag, main
    from support import REPO, install_prefix

    monkeypatch.chdir(REPO)
    assert default_bag() == DEFAULT_DATASET  # a checkout: its own bag
    monkeypatch.chdir(tmp_path)
    installed = install_prefix() / "share" / "linear_slam_ros" / "bags" / "vicpark200"
    assert default_bag() == installed
    assert sorted(p.name for p in installed.iterdir()) == ["metadata.yaml", "vicpark200.mcap"]
    assert (installed / "vicpark200.mcap").read_bytes() == (REPO / "bags" / "vicpark200" / "vicpark200.mcap").read_bytes()
    assert main(["--bag", "nowhere", "--out", str(tmp_path / "out")]) == 2
    assert "demo: dataset 'nowhere' is neither a folder nor a .tar.xz archive" in capsys.readouterr().err
    assert not (tmp_path / "out").exists()


def test_the_demo_reads_a_global_map_beyond_the_inputs_condition_bound():
    """The node's outputs are read without the inputs' condition bound (a large map's end frame exceeds it)."""
    import numpy as np

    from linear_slam_ros.core.errors import InvalidMapError
    from linear_slam_ros.core.local_map import POSE, LocalMap, to_dense
    from linear_slam_ros.ros.demo import decode_global_map
    from msg_adapters import MAP_KIND_GLOBAL, decode_map, encode_map
    from msg_adapters.bags import bag_parts, deserialize, serialize

    info = np.diag([1e11, 1e11, 1e11, 1e-4, 1e-4, 1e-4])  # condition number 1e15, every entry within bounds
    local_map = LocalMap.trusted(2, 0, 2, np.array([1, 2]), np.array([POSE, POSE], dtype=np.int8), np.arange(6.0), info)
    raw = serialize(encode_map(local_map, 7, map_kind=MAP_KIND_GLOBAL))
    with pytest.raises(InvalidMapError, match=r"too ill-conditioned .* above the limit max_condition = 1e\+14"):
        decode_map(*bag_parts(deserialize(raw)))
    decoded = decode_global_map(raw)
    np.testing.assert_array_equal(decoded.local_map.x, local_map.x)
    np.testing.assert_array_equal(to_dense(decoded.local_map.info), info)


def test_a_bag_given_alone_is_scored_against_its_own_maps(tmp_path, monkeypatch, capsys):
    """--bag OTHER without --dataset was scored against VicPark200's maps (a FrameError, no report)."""
    from linear_slam_ros.ros import demo

    seen: list[tuple[object, object]] = []

    def fake_run_demo(dataset, bag, *rest, **kwargs):
        seen.append((dataset, bag))
        return {"n_submaps_joined": 1, "n_submaps_sent": 1, "joiner_exit_code": 0}

    monkeypatch.setattr(demo, "run_demo", fake_run_demo)
    other = tmp_path / "other_bag"
    assert demo.main(["--bag", str(other), "--out", str(tmp_path / "o")]) == 0
    assert demo.main(["--bag", str(other), "--dataset", "synthetic:city2d-20", "--out", str(tmp_path / "o")]) == 0
    assert demo.main(["--out", str(tmp_path / "o")]) == 0
    assert [(str(d), str(b)) for d, b in seen] == [
        (str(other), str(other)), ("synthetic:city2d-20", str(other)), ("bags/vicpark200", "bags/vicpark200"),
    ]


def test_bench_node_refuses_an_unknown_stream_or_mode_before_measuring_anything(tmp_path, capsys):
    from linear_slam_ros.ros.bench_node import main

    for argv, message in (
        (["--only", "city2d-2000O"], "--only city2d-2000O: no such stream"),
        (["--mode", "bogus"], "argument --mode: invalid choice: 'bogus'"),
    ):
        with pytest.raises(SystemExit) as stop:
            main([*argv, "--datasets-dir", str(tmp_path / "none"), "--out", str(tmp_path / "out")])
        assert stop.value.code == 2 and message in capsys.readouterr().err
    assert not (tmp_path / "out").exists()  # node.md was overwritten with an empty table
