"""The offline command line: outputs, report, error exit code."""

from __future__ import annotations

import json
import logging

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


# ------------------------------------------------------------------ formats, errors and help (issue 14)


def _pose_only_dataset(tmp_path, dim=2):
    import numpy as np

    from linear_slam_ros.evaluation.synthetic import exact_pose_graph_maps, make_world
    from linear_slam_ros.io.datasets import MapKind
    from support import write_dataset

    rng = np.random.default_rng(7)
    kind = MapKind.PG2D if dim == 2 else MapKind.PG3D
    write_dataset(exact_pose_graph_maps(make_world(dim, 20, 0, rng), rng), tmp_path / "pg", kind)
    return tmp_path / "pg"


def _tum_rows(path):
    import numpy as np

    return np.array([[float(v) for v in line.split(" ")] for line in path.read_text().splitlines() if not line.startswith("#")])


@pytest.mark.parametrize("command", ["join", "refine"])
def test_format_tum_and_g2o(command, tmp_path):
    import numpy as np

    from linear_slam_ros.pose_graph.g2o import read_g2o, read_g2o_file

    out = tmp_path / "o"
    assert main([command, str(_pose_only_dataset(tmp_path)), "--out", str(out), "--format", "reference", "tum", "g2o"]) == 0
    poses = read_rows(out / "poses.txt")
    tum = _tum_rows(out / "poses.tum")
    assert tum.shape == (len(poses), 8) and tum[:, 0].tolist() == [float(k) for k in sorted(poses)]
    np.testing.assert_allclose(np.linalg.norm(tum[:, 4:], axis=1), 1.0, atol=1e-15)
    g2o = read_g2o_file(out / "graph.g2o")
    estimates = g2o.poses()
    assert sorted(estimates) == sorted(poses)
    for k, x in poses.items():
        np.testing.assert_array_equal(estimates[k], x)  # 2D: written and read back exactly
    assert read_g2o(out / "graph.g2o").n_edges > len(poses) - 1
    only_tum = tmp_path / "t"
    assert main([command, str(_pose_only_dataset(tmp_path)), "--out", str(only_tum), "--format", "tum"]) == 0
    assert sorted(p.name for p in only_tum.iterdir()) == ["poses.tum", "report.json"]


def test_se3_g2o_file_is_joined(tmp_path):
    import numpy as np

    from linear_slam_ros.core.geometry import wrap_angle
    from linear_slam_ros.io.datasets import read_dataset
    from linear_slam_ros.pose_graph.chunks import graph_from_local_maps
    from linear_slam_ros.pose_graph.g2o import write_g2o

    dataset = read_dataset(_pose_only_dataset(tmp_path, dim=3))
    write_g2o(tmp_path / "pg3.g2o", graph_from_local_maps(dataset.maps))
    assert main(["join", str(tmp_path / "pg"), "--out", str(tmp_path / "a")]) == 0
    assert main(["join", str(tmp_path / "pg3.g2o"), "--out", str(tmp_path / "b"), "--format", "reference", "tum"]) == 0
    report_a = json.loads((tmp_path / "a" / "report.json").read_text())
    report_b = json.loads((tmp_path / "b" / "report.json").read_text())
    assert report_b["kind"] == "3DPG" and report_b["n_submaps"] == report_a["n_submaps"] == 20
    assert report_b["chi2"] == pytest.approx(report_a["chi2"], abs=1e-9)
    a, b = read_rows(tmp_path / "a" / "poses.txt"), read_rows(tmp_path / "b" / "poses.txt")
    assert sorted(a) == sorted(b)
    for k in a:  # angles near pi may come out on either side
        np.testing.assert_allclose(np.r_[b[k][:3] - a[k][:3], wrap_angle(b[k][3:] - a[k][3:])], 0.0, atol=1e-9)
    assert _tum_rows(tmp_path / "b" / "poses.tum").shape == (21, 8)
    assert main(["join", str(tmp_path / "pg3.g2o"), "--kind", "2DPG", "--out", str(tmp_path / "c")]) == 2


def test_lago_refine_writes_the_refined_poses(tmp_path):
    import numpy as np

    from linear_slam_ros.evaluation.nonlinear import gauss_newton
    from linear_slam_ros.pose_graph.chunks import edge_maps
    from linear_slam_ros.pose_graph.g2o import read_g2o, write_g2o
    from linear_slam_ros.pose_graph.graph import PoseGraph
    from linear_slam_ros.pose_graph.lago import lago

    rng = np.random.default_rng(11)
    pairs = [(k, k + 1) for k in range(12)] + [(0, 6), (3, 11), (12, 2)]
    z = np.array([[1.0, 0.1, 0.5] for _ in pairs]) + rng.normal(scale=0.05, size=(len(pairs), 3))
    write_g2o(tmp_path / "g.g2o", PoseGraph.from_edges([a for a, _ in pairs], [b for _, b in pairs], z, [np.eye(3)] * len(pairs)))
    graph = read_g2o(tmp_path / "g.g2o")
    expected = gauss_newton(lago(graph).map, edge_maps(graph)).map
    out = tmp_path / "o"
    assert main(["lago", str(tmp_path / "g.g2o"), "--refine", "--out", str(out), "--format", "reference", "tum", "g2o"]) == 0
    report = json.loads((out / "report.json").read_text())
    assert report["poses_written"] == "nls" and report["nls_chi2"] < report["chi2"]
    poses = read_rows(out / "poses.txt")
    for i, k in enumerate(expected.ids.tolist()):
        np.testing.assert_array_equal(poses[k], expected.x[expected.scalar_slice(i)])
    assert _tum_rows(out / "poses.tum").shape == (13, 8)
    assert sorted(read_g2o(out / "graph.g2o").pose_ids.tolist()) == list(range(13))
    assert main(["lago", str(tmp_path / "g.g2o"), "--out", str(tmp_path / "l")]) == 0
    assert json.loads((tmp_path / "l" / "report.json").read_text())["poses_written"] == "lago"
    assert read_rows(tmp_path / "l" / "poses.txt")[5].tolist() != poses[5].tolist()


def test_pose_formats_need_poses(tmp_path, caplog):
    archive = str(dataset_archive("8240_data_50_local_maps"))
    assert main(["join", archive, "--map-type", "feature-only", "--format", "tum", "--out", str(tmp_path / "a")]) == 2
    assert "--format tum writes poses; feature-only maps hold none" in caplog.text
    assert main(["join", archive, "--format", "g2o", "--out", str(tmp_path / "b")]) == 2
    assert "--format g2o writes a pose graph; 8240_data_50_local_maps is a pose-feature dataset (2DPF)" in caplog.text


def _run_cli(*args, cache):
    import os
    import subprocess
    import sys

    env = {**os.environ, "LINEAR_SLAM_CACHE": str(cache)}
    return subprocess.run([sys.executable, "-m", "linear_slam_ros", *args], capture_output=True, text=True, env=env, timeout=120,
                          check=False)


def _one_error_line(result):
    assert result.returncode == 2, result.stderr
    assert "Traceback" not in result.stderr
    lines = result.stderr.splitlines()
    assert len(lines) == 1, result.stderr
    assert lines[0].startswith("ERROR linear_slam_ros: ")
    return lines[0]


def test_bad_input_is_one_stderr_line_and_exit_2(tmp_path):
    """Truncated archive, corrupt archive, garbage line, missing files: one line naming the file, exit code 2."""
    data = dataset_archive("Intel").read_bytes()
    (tmp_path / "cut.tar.xz").write_bytes(data[: len(data) // 3])
    corrupt = bytearray(data)
    corrupt[5000:5100] = b"x" * 100
    (tmp_path / "bad.tar.xz").write_bytes(bytes(corrupt))
    folder = _pose_only_dataset(tmp_path)
    lines = (folder / "localmap_3.txt").read_text().splitlines()
    lines[6] = lines[6] + " #"
    (folder / "localmap_3.txt").write_text("\n".join(lines) + "\n")
    cache, out = tmp_path / "cache", str(tmp_path / "o")
    line = _one_error_line(_run_cli("join", str(tmp_path / "cut.tar.xz"), "--out", out, cache=cache))
    assert line.endswith("cut.tar.xz: the archive is truncated")
    assert "bad.tar.xz: " in _one_error_line(_run_cli("refine", str(tmp_path / "bad.tar.xz"), "--out", out, cache=cache))
    line = _one_error_line(_run_cli("join", str(folder), "--out", out, cache=cache))
    assert line.endswith(f"{folder / 'localmap_3.txt'}:7: '#' is not a number")
    line = _one_error_line(_run_cli("join", "missing", "--out", out, cache=cache))
    assert "'missing' is neither a folder nor a .tar.xz archive" in line
    line = _one_error_line(_run_cli("lago", str(tmp_path / "none.g2o"), "--out", out, cache=cache))
    assert "none.g2o: [Errno 2] No such file or directory" in line
    good = _pose_only_dataset(tmp_path / "good")
    line = _one_error_line(_run_cli("join", str(good), "--initial-state", str(tmp_path / "no.npz"), "--out", out, cache=cache))
    assert "no.npz" in line


def test_help_shows_defaults(capsys):
    cases = (("join", "(default: dc)"), ("lago", "(default: ['reference'])"), ("benchmark", "(default: out/benchmark)"))
    for command, expected in cases:
        with pytest.raises(SystemExit) as stop:
            main([command, "--help"])
        assert stop.value.code == 0
        assert expected in capsys.readouterr().out


def test_a_folder_that_skips_numbers_is_joined_with_the_gap_as_islands(tmp_path, caplog):
    from linear_slam_ros.io.datasets import resolve_dataset_dir

    folder = resolve_dataset_dir(dataset_archive("8240_data_50_local_maps"))
    gap = tmp_path / "gap"
    gap.mkdir()
    for f in folder.glob("localmap_*.txt"):
        if f.name not in ("localmap_20.txt", "localmap_33.txt"):  # two submaps lost
            (gap / f.name).write_text(f.read_text())
    out = tmp_path / "out"
    assert main(["join", str(gap), "--method", "online-dc", "--out", str(out)]) == 0
    report = json.loads((out / "report.json").read_text())
    # the part after 20 links back through common features; the part after 33 never meets the rest again
    assert report["n_submaps"] == 48 and report["n_islands"] == 2 and report["island_sizes"] == [36, 12]
    assert "2 local map(s) missing (numbers [20, 33])" in caplog.text
    assert "the results hold the main island (the first submap's): 36 submaps" in caplog.text
    assert 0 in read_rows(out / "poses.txt") and report["chi2"] > 0  # χ² of the main island's own submaps


def test_two_datasets_join_as_two_robots(tmp_path, caplog):
    from linear_slam_ros.io.datasets import resolve_dataset_dir

    folder = resolve_dataset_dir(dataset_archive("8240_data_50_local_maps"))
    halves = [tmp_path / "a", tmp_path / "b"]
    for h in halves:
        h.mkdir()
    for i in range(1, 51):  # robot b's stream starts at its own localmap_1
        target = halves[0] / f"localmap_{i}.txt" if i <= 25 else halves[1] / f"localmap_{i - 25}.txt"
        target.write_text((folder / f"localmap_{i}.txt").read_text())
    out = tmp_path / "out"
    assert main(["join", str(halves[0]), str(halves[1]), "--robots", "--method", "online-dc", "--out", str(out)]) == 0
    report = json.loads((out / "report.json").read_text())
    assert report["n_submaps"] == 50 and report["n_islands"] == 1, report
    poses = read_rows(out / "poses.txt")
    assert any(k >= 2**32 for k in poses) and 0 in poses  # robot 1's poses, renamed; robot 0's as they were
    assert main(["join", str(halves[0]), str(halves[1]), "--out", str(tmp_path / "x")]) == 2
    assert "2 datasets given: joining several needs --robots" in caplog.text


def _subset(folder, target, numbers, offset=0):
    """Copy ``localmap_<i>.txt`` for ``i`` in ``numbers`` into ``target`` as ``localmap_<i - offset>.txt``."""
    target.mkdir()
    for i in numbers:
        (target / f"localmap_{i - offset}.txt").write_text((folder / f"localmap_{i}.txt").read_text())
    return target


def test_closures_still_held_at_the_end_are_left_out_of_the_chi2_and_the_refinement(tmp_path):
    """Intel's first 100 submaps hold closures to poses the chain never reaches: they were never joined."""
    from linear_slam_ros.io.datasets import resolve_dataset_dir

    intel = resolve_dataset_dir(dataset_archive("Intel"))
    first = _subset(intel, tmp_path / "first", range(1, 101))
    for args in (["join", "--hold-closures"], ["join", "--gate-probability", "0.99999999"], ["refine", "--hold-closures"]):
        out = tmp_path / "_".join(a.strip("-") for a in args)
        assert main([args[0], str(first), "--method", "online-dc", *args[1:], "--out", str(out)]) == 0, args
        report = json.loads((out / "report.json").read_text())
        assert report["n_held"] > 300 and report["chi2_submaps"] == 100 and report["chi2"] < 1e-6, report  # a tree left
        assert len(read_rows(out / "poses.txt")) == 101  # the chain's poses: no estimate for the closures' targets
    islands = _subset(intel, tmp_path / "islands", [1, 3])  # two islands of one submap each, closures held
    assert main(["join", str(islands), "--method", "online-dc", "--hold-closures", "--out", str(tmp_path / "i")]) == 0
    report = json.loads((tmp_path / "i" / "report.json").read_text())
    assert report["n_islands"] == 2 and report["chi2_submaps"] == 1


def test_initial_state_then_a_stream_that_skips_numbers_equals_one_run(tmp_path):
    from linear_slam_ros.io.datasets import resolve_dataset_dir

    folder = resolve_dataset_dir(dataset_archive("8240_data_50_local_maps"))
    whole = _subset(folder, tmp_path / "whole", [i for i in range(1, 51) if i != 30])
    first = _subset(folder, tmp_path / "first", range(1, 26))
    rest = _subset(folder, tmp_path / "rest", [i for i in range(26, 51) if i != 30], offset=25)  # 1-4, 6-25
    common = ["--method", "online-dc"]
    state = tmp_path / "first.npz"
    assert main(["join", str(whole), *common, "--out", str(tmp_path / "o_whole")]) == 0
    assert main(["join", str(first), *common, "--out", str(tmp_path / "o1"), "--save-state", str(state)]) == 0
    assert main(["join", str(rest), *common, "--out", str(tmp_path / "o2"), "--initial-state", str(state)]) == 0
    assert (tmp_path / "o2" / "poses.txt").read_text() == (tmp_path / "o_whole" / "poses.txt").read_text()
    report = json.loads((tmp_path / "o2" / "report.json").read_text())
    assert report["n_submaps"] == 24 and report["chi2_submaps"] == 24  # the χ² of the maps given only


def test_option_combinations_that_cannot_work_exit_2_with_the_reason(tmp_path, caplog):
    from linear_slam_ros.io.datasets import resolve_dataset_dir

    archive = str(dataset_archive("8240_data_50_local_maps"))
    gap = _subset(resolve_dataset_dir(dataset_archive("8240_data_50_local_maps")), tmp_path / "gap", [1, 2, 4])
    state = tmp_path / "s.npz"
    assert main(["join", archive, "--method", "online-dc", "--out", str(tmp_path / "a"), "--save-state", str(state)]) == 0
    cases = [
        (["join", str(gap), "--method", "dc"], "the local maps skip numbers (lost submaps) and are joined as islands, "
                                               "which method 'dc' with map type 'as-is' cannot do"),
        (["join", archive, archive, "--robots", "--method", "dc"], "the local maps come from several robots"),
        (["join", archive, "--method", "dc", "--hold-closures"], "parameter hold_closures=True: mode 'dc' with map_type "
                                                                 "'as-is' cannot hold loop closures"),
        (["join", archive, "--method", "online-dc", "--map-type", "feature-only", "--gate-probability", "0.99"],
         "parameter gate_probability=0.99: mode 'online-dc' with map_type 'feature-only' cannot gate"),
        (["refine", archive, "--method", "online-dc", "--initial-state", str(state)],
         "refine / join --refine with --initial-state: a saved state holds its joined map"),
        (["join", archive, "--method", "online-dc", "--refine", "--initial-state", str(state)], "cannot be refined"),
        (["benchmark", "--only", "NoSuch", "--datasets-dir", str(tmp_path)], "benchmark: no *.tar.xz dataset named NoSuch"),
        # one name of two matching: the typo is not dropped silently (nothing is read before the check)
        (["benchmark", "--only", "A", "VicPark200", "--datasets-dir", str(tmp_path / "ds")],
         "benchmark: no *.tar.xz dataset named VicPark200"),
    ]
    (tmp_path / "ds").mkdir()
    (tmp_path / "ds" / "A.tar.xz").write_bytes(b"")
    for argv, message in cases:
        caplog.clear()
        assert main([*argv, "--out", str(tmp_path / "x")]) == 2, argv
        assert message in caplog.text, (argv, caplog.text)
    with pytest.raises(SystemExit) as stop:
        main(["benchmark", "--methods", "bogus"])
    assert stop.value.code == 2


def test_g2o_output_holds_the_result_s_poses_only(tmp_path, caplog):
    from linear_slam_ros.io.datasets import resolve_dataset_dir
    from linear_slam_ros.pose_graph.g2o import read_g2o

    gap = _subset(resolve_dataset_dir(dataset_archive("Intel")), tmp_path / "gap", [i for i in range(1, 101) if i != 50])
    out = tmp_path / "o"
    assert main(["join", str(gap), "--method", "online-dc", "--format", "reference", "g2o", "--out", str(out)]) == 0
    graph = read_g2o(out / "graph.g2o")
    assert sorted(graph.pose_ids.tolist()) == sorted(read_rows(out / "poses.txt"))  # no vertex written at the origin
    assert "poses without an estimate (other islands, loop closures still held)" in caplog.text


def test_refine_with_the_gate_and_islands_refines_what_the_joins_fused(tmp_path, monkeypatch):
    """With islands, the main island's original maps were refined: the gate's splits were back in the objective."""
    import linear_slam_ros.cli.main as cli
    from linear_slam_ros.io.datasets import resolve_dataset_dir

    gap = _subset(resolve_dataset_dir(dataset_archive("Intel")), tmp_path / "gap", [i for i in range(1, 801) if i != 796])
    refined: list[list[object]] = []
    real = cli.refine
    monkeypatch.setattr(cli, "refine", lambda initial, maps, *a, **k: refined.append(list(maps)) or real(initial, maps, *a, **k))
    out = tmp_path / "o"
    assert main(["refine", str(gap), "--method", "online-dc", "--gate-probability", "0.99", "--out", str(out)]) == 0
    report = json.loads((out / "report.json").read_text())
    assert report["n_islands"] > 1 and report["gated"], report.get("n_islands")
    split = {(g["submap"], v) for g in report["gated"] for v in g["variables"]}
    for m in refined[0]:
        seq = int(m.name.split("_")[1].split("/")[0])  # localmap_<i>, or localmap_<i>/closure_<target>
        assert not any((seq, int(pid)) in split for pid in m.pose_ids.tolist() if "/closure_" not in m.name), m.name


def test_a_g2o_vertex_no_edge_names_is_left_out_with_a_warning(tmp_path, caplog):
    """It was dropped without a word (only --format g2o said anything)."""
    edges = "EDGE_SE2 0 1 1 0 0 100 0 0 100 0 1000\nEDGE_SE2 1 2 1 0 0 100 0 0 100 0 1000\n"
    (tmp_path / "iso.g2o").write_text("".join(f"VERTEX_SE2 {i} {i} 0 0\n" for i in range(4)) + edges)
    with caplog.at_level(logging.WARNING):
        assert main(["join", str(tmp_path / "iso.g2o"), "--out", str(tmp_path / "out")]) == 0
    assert "1 vertices no edge names are left out (vertex 3)" in caplog.text
    assert sorted(read_rows(tmp_path / "out" / "poses.txt")) == [0, 1, 2]
