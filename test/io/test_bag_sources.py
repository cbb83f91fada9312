"""The committed bags stand in for ../shared/datasets: the CLI reads a bag wherever it reads a dataset,
the bags hold the archives' maps bit for bit, and the suite needs nothing outside the repository.

The full proof runs the README's two commands in a fresh clone with no ../shared beside it
(``.ci/fresh_clone_check``, slow); the fast tests here check the pieces it rests on.
"""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import scipy.sparse as sp

import support
from linear_slam_ros.cli.main import main, read_bag, read_source
from linear_slam_ros.core.errors import DatasetError
from linear_slam_ros.io.datasets import MapKind, read_dataset
from linear_slam_ros.ros.bag_from_dataset import make_bag
from linear_slam_ros.ros.bagio import read_messages, write_messages
from msg_adapters.bags import CUSTOM_DATASET, CUSTOM_KIND, bag_custom_data, is_bag
from support import BAGS, CACHE, COMMITTED_BAGS, DATASETS, REPO, committed_bag

VICPARK_DC_CHI2 = 3645.46  # shared/datasets/README.md, paper Table 2: D&C on VicPark_200
MAX_TOTAL_BYTES = 20 * 10**6
LARGE = {"manhattanOlson3500", "sphere2500", "Simu_3D_870_Loop"}  # the long reads compare in test-slow


def _dense(info: object) -> np.ndarray:
    return info.toarray() if sp.issparse(info) else np.asarray(info)  # type: ignore[union-attr]


def _same_maps(a, b) -> None:
    assert len(a) == len(b)
    for m, n in zip(a, b, strict=True):
        assert (m.dim, m.frame_id, m.end_id) == (n.dim, n.frame_id, n.end_id)
        assert np.array_equal(m.ids, n.ids) and np.array_equal(m.kinds, n.kinds)
        assert np.array_equal(m.x, n.x)  # bit for bit
        assert sp.issparse(m.info) == sp.issparse(n.info) and np.array_equal(_dense(m.info), _dense(n.info))


def _bag_size(bag: Path) -> int:
    return sum(f.stat().st_size for f in bag.iterdir() if f.is_file())


@pytest.mark.parametrize("name", [pytest.param(n, marks=pytest.mark.slow) if n in LARGE else n for n in COMMITTED_BAGS])
def test_each_committed_bag_holds_its_dataset_bit_for_bit(name):
    bag = committed_bag(name)
    assert bag is not None, f"bags/{COMMITTED_BAGS[name]} is missing: run `make bags`"
    from_bag = read_source(bag)
    assert from_bag.name == bag.name and from_bag.kind.value == bag_custom_data(bag)[CUSTOM_KIND]
    assert bag_custom_data(bag)[CUSTOM_DATASET] == name
    archive = DATASETS / f"{name}.tar.xz"
    if not archive.exists():  # a fresh clone: the bag is all there is (the README table says what it holds)
        assert len(from_bag.maps) > 0
        return
    dataset = read_dataset(archive, cache_dir=CACHE)
    assert from_bag.kind is dataset.kind
    _same_maps(from_bag.maps, dataset.maps)


def test_join_bag_gives_the_archives_chi2(tmp_path):
    """Acceptance: `join bags/vicpark200 --method dc` gives χ² 3645.46, exactly as from the archive."""
    out = tmp_path / "bag"
    assert main(["join", str(BAGS / "vicpark200"), "--method", "dc", "--out", str(out)]) == 0
    report = json.loads((out / "report.json").read_text())
    assert round(report["chi2"], 2) == VICPARK_DC_CHI2
    assert (report["dataset"], report["kind"], report["n_submaps"]) == ("vicpark200", "2DPF", 200)
    archive = DATASETS / "VicPark_200_local_maps.tar.xz"
    if archive.exists():
        assert main(["join", str(archive), "--method", "dc", "--out", str(tmp_path / "archive")]) == 0
        from_archive = json.loads((tmp_path / "archive" / "report.json").read_text())
        assert report["chi2"] == from_archive["chi2"]
        assert (out / "poses.txt").read_text() == (tmp_path / "archive" / "poses.txt").read_text()


def test_a_bag_of_pose_graph_chunks_joins_like_its_local_maps(tmp_path):
    """One local map per chunk (stars: converted exactly), and five (chains with loops: LAGO)."""
    intel = BAGS / "Intel"
    chunks = tmp_path / "Intel_chunks1"
    make_bag(intel, chunks, as_pose_graph=True)
    assert {r.topic for r in read_messages(chunks)} == {"/pose_graph"}
    assert read_source(chunks).kind is MapKind.PG2D
    assert main(["join", str(intel), "--method", "dc", "--out", str(tmp_path / "maps")]) == 0
    assert main(["join", str(chunks), "--method", "dc", "--out", str(tmp_path / "chunks")]) == 0
    maps = json.loads((tmp_path / "maps" / "report.json").read_text())
    chunked = json.loads((tmp_path / "chunks" / "report.json").read_text())
    assert chunked["n_submaps"] == maps["n_submaps"] == 942
    assert chunked["chi2"] == pytest.approx(maps["chi2"], rel=1e-9)
    five = tmp_path / "Intel_chunks5"
    make_bag(intel, five, as_pose_graph=True, maps_per_chunk=5)
    assert main(["join", str(five), "--method", "online-dc", "--out", str(tmp_path / "five")]) == 0
    assert json.loads((tmp_path / "five" / "report.json").read_text())["n_submaps"] == 189  # ceil(942 / 5)


def test_bag_reading_errors_name_the_bag(tmp_path):
    vicpark = BAGS / "vicpark200"
    with pytest.raises(DatasetError, match="is a rosbag2 bag, not a dataset folder"):
        read_dataset(vicpark)
    with pytest.raises(DatasetError, match="holds 2DPF maps, not 2DPG"):
        read_bag(vicpark, kind="2DPG")
    records = list(read_messages(vicpark))[:3]
    only_global = tmp_path / "global_only"
    write_messages(only_global, [("global_map", r.time_ns, r.raw) for r in records], latched={"global_map"})
    with pytest.raises(DatasetError, match=f"bag {re.escape(str(only_global))}: no local_map or pose_graph messages"):
        read_source(only_global)
    resent = tmp_path / "resent"  # a message sent again is skipped, as the node skips it; order is by seq
    write_messages(resent, [(r.topic, r.time_ns, r.raw) for r in [records[1], records[0], records[1], records[2]]])
    assert [m.frame_id for m in read_source(resent).maps] == [m.frame_id for m in read_source(vicpark).maps[:3]]
    broken = tmp_path / "broken"
    broken.mkdir()
    (broken / "metadata.yaml").write_text("not: a bag\n")
    assert is_bag(broken)
    assert _one_error(["join", str(broken), "--out", str(tmp_path / "o")]).startswith(f"cannot read bag {broken}")


def test_a_bag_of_several_robots_is_refused_and_foreign_types_are_ignored(tmp_path):
    """Each robot numbers its own submaps: merged by number, one robot's would replace the other's. A
    ``ros2 bag record -a`` may hold another type on a topic named ``local_map``: it is not a submap."""
    from rosbags.rosbag2 import StoragePlugin, Writer

    from linear_slam_ros.ros.bagio import qos
    from msg_adapters.bags import MSGTYPE, TYPESTORE

    records = list(read_messages(BAGS / "vicpark200"))[:2]
    two = tmp_path / "two_robots"
    write_messages(two, [(f"/{robot}/local_map", r.time_ns, r.raw) for robot in ("a", "b") for r in records])
    with pytest.raises(DatasetError, match=f"bag {re.escape(str(two))}: submap topics of several namespaces "
                       "\\(/a/local_map, /b/local_map\\): one robot's stream per bag"):
        read_source(two)
    one = tmp_path / "one_robot"  # local_map and pose_graph of one namespace are one stream
    write_messages(one, [("/a/local_map", r.time_ns, r.raw) for r in records])
    assert len(read_source(one).maps) == 2

    foreign = tmp_path / "foreign"
    other_type = "std_msgs/msg/String"
    writer = Writer(foreign, version=9, storage_plugin=StoragePlugin.MCAP)
    with writer:
        ours = writer.add_connection("/local_map", MSGTYPE, typestore=TYPESTORE, offered_qos_profiles=[qos(False)])
        other = writer.add_connection("/nav/local_map", other_type, typestore=TYPESTORE, offered_qos_profiles=[qos(False)])
        for r in records:
            writer.write(ours, r.time_ns, r.raw)
            text = TYPESTORE.types[other_type](data="not a submap")
            writer.write(other, r.time_ns + 1, bytes(TYPESTORE.serialize_cdr(text, other_type)))
    got = read_source(foreign)
    assert [m.frame_id for m in got.maps] == [m.frame_id for m in read_source(BAGS / "vicpark200").maps[:2]]


def test_a_bag_of_two_kinds_or_of_a_kind_its_maps_are_not_is_refused(tmp_path):
    planar = list(read_messages(BAGS / "vicpark200"))[:2]
    spatial = list(read_messages(committed_bag("Simu_3D_870_Loop")))[2:3]  # its third submap: seq 3
    mixed = tmp_path / "mixed"
    write_messages(mixed, [(r.topic, r.time_ns, r.raw) for r in planar + spatial])
    with pytest.raises(DatasetError, match="submap seq 3 is 3D, seq 1 2D: one bag holds one map kind"):
        read_source(mixed)
    told = tmp_path / "told_pose_graph"
    write_messages(told, [(r.topic, r.time_ns, r.raw) for r in planar], custom_data={CUSTOM_KIND: "2DPG"})
    with pytest.raises(DatasetError, match="its metadata names map kind '2DPG' \\(pose graph\\), its maps hold features"):
        read_source(told)


def _one_error(argv: list[str]) -> str:
    result = subprocess.run([sys.executable, "-m", "linear_slam_ros", *argv], capture_output=True, text=True, cwd=REPO)
    assert result.returncode == 2 and len(result.stderr.splitlines()) == 1, result.stderr
    return result.stderr.split(": ", 1)[1].strip()


def test_without_shared_the_datasets_come_from_the_committed_bags(tmp_path, monkeypatch):
    """What the suite does on a fresh clone: LINEAR_SLAM_DATASETS at an empty folder's missing child."""
    monkeypatch.setattr(support, "DATASETS", tmp_path / "no_shared")
    assert support.dataset_source("VicPark_200_local_maps") == BAGS / "vicpark200"
    archive = support.dataset_archive("Intel")  # an archive written once from the committed bag
    assert archive.suffix == ".xz" and archive.is_relative_to(CACHE)
    _same_maps(read_dataset(archive, cache_dir=tmp_path / "cache").maps, read_source(BAGS / "Intel").maps)
    with pytest.raises(pytest.skip.Exception, match=r"needs \.\./shared/datasets: VicPark_6898_local_maps"):
        support.dataset_source("VicPark_6898_local_maps")
    monkeypatch.setattr(support, "DATASETS", tmp_path)  # ../shared there but incomplete: fail, never skip
    with pytest.raises(pytest.fail.Exception, match="VicPark_6898_local_maps.tar.xz is missing"):
        support.dataset_source("VicPark_6898_local_maps")


def test_the_suite_collects_without_shared(tmp_path):
    """Every test module imports and collects with the datasets folder absent (no import-time reads)."""
    env = {**os.environ, "LINEAR_SLAM_DATASETS": str(tmp_path / "no_shared")}
    result = subprocess.run(
        [sys.executable, "-m", "pytest", "--collect-only", "-q", "-m", "", "-p", "no:cacheprovider"],
        capture_output=True, text=True, cwd=REPO, env=env, timeout=300,
    )
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]
    assert re.search(r"\d+ tests collected", result.stdout), result.stdout[-2000:]


def test_committed_bags_are_listed_sized_and_let_in_by_gitignore():
    makefile = (REPO / "Makefile").read_text()
    listed = re.search(r"^DATASET_BAGS := (.*)$", makefile, re.M)
    assert listed is not None
    assert {"vicpark200", *listed.group(1).split()} == set(COMMITTED_BAGS.values())
    readme = (BAGS / "README.md").read_text()
    total = 0
    for bag in COMMITTED_BAGS.values():
        size = _bag_size(BAGS / bag)
        total += size
        assert re.search(rf"^\| `{re.escape(bag)}` \|.*\| {size:,} \|$", readme, re.M), f"bags/README.md: {bag} {size:,}"
    assert f"**{total:,}**" in readme and total < MAX_TOTAL_BYTES
    if not (REPO / ".git").exists():
        pytest.skip("not a git checkout: .gitignore cannot be asked")
    committed = [str(BAGS / b / f) for b in COMMITTED_BAGS.values() for f in ("metadata.yaml", f"{b}.mcap")]
    generated = [str(BAGS / n / "metadata.yaml") for n in ("city2d-20000", "VicPark_6898_local_maps", "Intel_chunks5")]
    ignored = subprocess.run(["git", "check-ignore", *committed, *generated], capture_output=True, text=True, cwd=REPO)
    assert sorted(ignored.stdout.split()) == sorted(generated)


@pytest.mark.slow
def test_make_run_and_make_test_pass_on_a_fresh_clone_without_shared():
    """Acceptance: the README's two commands in a fresh clone with no ../shared (``.ci/fresh_clone_check``)."""
    result = subprocess.run([str(REPO / ".ci" / "fresh_clone_check")], capture_output=True, text=True, cwd=REPO, timeout=3600)
    assert result.returncode == 0, result.stdout[-4000:] + result.stderr[-4000:]
    assert "make run and make test pass on a fresh clone without ../shared" in result.stdout
