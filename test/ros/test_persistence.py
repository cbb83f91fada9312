"""Persistence through the installed node: kill -9 and resume, corrupt files, save -> load -> continue.

Every run here is compared with the offline core on the same submaps (the end-to-end replay test
shows that an uninterrupted node run equals it to 1e-9).
"""

from __future__ import annotations

import contextlib
import json
import os
import signal
import time
import uuid

import numpy as np
import pytest
import rclpy
from std_msgs.msg import Float64MultiArray

from linear_slam_ros.evaluation.runner import run_join
from linear_slam_ros.joiner.snapshot import FORMAT_VERSION
from linear_slam_ros.ros.bagio import read_messages
from linear_slam_ros.ros.qos import inbound_qos
from linear_slam_ros.ros.spin import spin_until
from ros_support import call_trigger, global_map_subscription, wait_for_global_map
from ros_support import dataset_bag as _bag

KILLS = 10


@contextlib.contextmanager
def _fresh_node():
    """A node of a DDS participant of its own, for one joiner's lifetime (killed or not).

    The test once used one long-lived node for all eleven joiners it starts and kills -9; the last
    joiner then sometimes received nothing (discovered, its subscription matched, no sample
    acknowledged within 60 s, no map within 300 s: seen in a fresh-clone run, a full local run and,
    on UDP only, one of two runs of this test alone; the joiner's own log showed nothing received).
    The cause was not pinned down; the suspect is the long-lived participant's state about the
    killed ones (a killed participant announces nothing, and its proxy stays until its lease ends),
    which a participant that never knew them cannot have. On UDP only (loopback:
    ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST), as are the joiners: a joiner killed -9 leaves no
    shared-memory segment behind.
    """
    context = rclpy.Context()
    rclpy.init(context=context)
    n = rclpy.create_node(f"test_{uuid.uuid4().hex[:8]}", context=context)
    try:
        yield n
    finally:
        n.destroy_node()
        rclpy.try_shutdown(context=context)


@pytest.fixture
def udp_only(rclpy_session, monkeypatch):
    """Fast DDS on UDP only for the nodes made and the joiners started in the test (read at participant creation)."""
    monkeypatch.setenv("FASTDDS_BUILTIN_TRANSPORTS", "UDPv4")


def _assert_equals_offline(final, maps, mode):
    offline = run_join(maps, mode).result
    assert final.n_submaps == len(maps) and final.stats["n_joined"] == len(maps), "submaps lost"
    assert final.stats["n_rejected"] == 0
    np.testing.assert_array_equal(final.local_map.ids, offline.ids)
    np.testing.assert_allclose(final.local_map.x, offline.x, rtol=0, atol=1e-9)
    scale = np.abs(offline.info_dense()).max()
    np.testing.assert_allclose(final.local_map.info_dense() / scale, offline.info_dense() / scale, rtol=0, atol=1e-9)


def _publish_then_kill(node, joiner, records, rate_factor, instant):
    """Publish records at ``rate_factor`` times bag speed until ``instant`` s after the first, then kill -9 the joiner."""
    pub = node.create_publisher(Float64MultiArray, joiner.topic(records[0].topic), inbound_qos())
    assert spin_until(node, lambda: pub.get_subscription_count() > 0, 60.0, 0.01), "the joiner did not subscribe"
    start_wall, start_bag = time.monotonic(), records[0].time_ns
    for r in records:
        due = (r.time_ns - start_bag) / 1e9 / rate_factor
        if due >= instant:
            break
        pause = start_wall + due - time.monotonic()
        if pause > 0:
            time.sleep(pause)
        pub.publish(r.raw)
    pause = start_wall + instant - time.monotonic()
    if pause > 0:
        time.sleep(pause)
    os.kill(joiner.process.pid, signal.SIGKILL)
    joiner.process.wait(30)
    node.destroy_publisher(pub)


@pytest.mark.parametrize(
    ("name", "mode", "rate_factor"),
    [
        pytest.param("VicPark_200_local_maps", "sequential", 5.0, id="VicPark200"),
        pytest.param("Intel", "online-dc", 40.0, id="Intel"),
    ],
)
def test_kill_9_at_random_instants_loses_nothing(name, mode, rate_factor, udp_only, start_joiner, read_benchmark, tmp_path):
    maps = read_benchmark(name).maps
    records = list(read_messages(_bag(name)))
    play_s = (records[-1].time_ns - records[0].time_ns) / 1e9 / rate_factor
    state_dir = tmp_path / "state"
    params = {"mode": mode, "state_dir": str(state_dir), "snapshot_period": 37, "publish_rate": 10.0}
    rng = np.random.default_rng(20261122)
    resumed = []
    for k, instant in enumerate(rng.uniform(0.0, play_s, KILLS)):
        joiner = start_joiner(**params)
        with _fresh_node() as node:
            _publish_then_kill(node, joiner, records, rate_factor, instant)
        assert joiner.process.returncode == -signal.SIGKILL, f"kill {k}: the joiner had already exited"
        output = joiner.stop()[1]
        if k > 0:  # every restart resumed what the killed node had (its log line says from where)
            lines = [line for line in output.splitlines() if "resumed from" in line]
            assert len(lines) == 1, output[-2000:]
            resumed.append(lines[0].split("resumed from ", 1)[1])
    print("\n".join(resumed))  # shown with -s: snapshots and journal records replayed at each restart
    joiner = start_joiner(**params)
    with _fresh_node() as node, global_map_subscription(node, joiner.topic("global_map")) as latest:
        joiner.play(node, records)  # the subscription first: before the last map is published
        final, _ = wait_for_global_map(
            node, joiner.topic("global_map"), lambda m: m.n_submaps == len(maps), 300.0, joiner, latest=latest
        )
    code, output = joiner.stop()
    assert code == 0, output[-3000:]
    assert "resumed from" in output
    _assert_equals_offline(final, maps, mode)


def _run_to_end(node, start_joiner, records, n, **params):
    joiner = start_joiner(**params)
    joiner.play(node, records)
    final, _ = wait_for_global_map(node, joiner.topic("global_map"), lambda m: m.n_submaps == n, 300.0, joiner)
    return joiner, final


def test_corrupt_snapshot_and_truncated_journal_fall_back(node, start_joiner, read_benchmark, tmp_path):
    name, mode = "VicPark_200_local_maps", "sequential"
    maps = read_benchmark(name).maps
    records = list(read_messages(_bag(name)))
    state_dir = tmp_path / "state"
    params = {"mode": mode, "state_dir": str(state_dir), "snapshot_period": 50, "publish_rate": 10.0}
    joiner, _ = _run_to_end(node, start_joiner, records[:120], 120, **params)
    assert joiner.stop()[0] == 0
    snapshots = sorted((state_dir / "snapshots").glob("state_*.npz"), key=lambda p: int(p.stem.split("_")[1]))
    assert len(snapshots) == 2
    newest = snapshots[-1]
    data = bytearray(newest.read_bytes())
    data[len(data) // 2] ^= 0xFF  # a flipped byte: checksum (or zip CRC) fails
    newest.write_bytes(bytes(data))
    journal = sorted((state_dir / "journal").glob("*.mcap"))[-1]
    with open(journal, "r+b") as fh:  # a kill in mid-write: the file ends inside a record
        fh.truncate(journal.stat().st_size - 7)

    joiner, final = _run_to_end(node, start_joiner, records, len(maps), **params)
    code, output = joiner.stop()
    assert code == 0, output[-3000:]
    assert newest.name in output and "falling back to an older point" in output
    _assert_equals_offline(final, maps, mode)


def test_snapshot_of_another_format_version_is_never_used(node, start_joiner, read_benchmark, tmp_path):
    import json

    name, mode = "VicPark_200_local_maps", "sequential"
    maps = read_benchmark(name).maps
    records = list(read_messages(_bag(name)))
    state_dir = tmp_path / "state"
    params = {"mode": mode, "state_dir": str(state_dir), "snapshot_period": 1000, "publish_rate": 10.0}
    joiner, _ = _run_to_end(node, start_joiner, records[:80], 80, **params)
    assert joiner.stop()[0] == 0
    for path in (state_dir / "snapshots").glob("state_*.npz"):
        with np.load(path, allow_pickle=False) as npz:
            arrays = {k: npz[k] for k in npz.files}
        header = json.loads(bytes(arrays["header"]).decode())
        header["version"] = 999
        arrays["header"] = np.frombuffer(json.dumps(header).encode(), dtype=np.uint8)
        with open(path, "wb") as fh:
            np.savez(fh, **arrays)
    joiner, final = _run_to_end(node, start_joiner, records, len(maps), **params)
    code, output = joiner.stop()
    assert code == 0, output[-3000:]
    assert f"format version 999, this build reads version {FORMAT_VERSION}" in output
    assert "an empty map and 80 journal record(s)" in output
    _assert_equals_offline(final, maps, mode)


def test_a_reset_stays_reset_when_its_snapshot_is_lost(node, start_joiner, read_benchmark, tmp_path):
    """``~/reset`` records where the new map starts (start.json) before the map is cleared: a restart whose
    newest snapshot is corrupt neither brings the cleared map back nor skips the new submaps (numbered
    from 1 again) as already handled."""
    name, mode = "VicPark_200_local_maps", "online-dc"
    maps = read_benchmark(name).maps
    records = list(read_messages(_bag(name)))
    state_dir = tmp_path / "state"
    params = {"mode": mode, "state_dir": str(state_dir), "snapshot_period": 20, "publish_rate": 10.0}
    joiner, _ = _run_to_end(node, start_joiner, records[:50], 50, **params)
    assert call_trigger(node, f"/{joiner.namespace}/joiner/reset").success
    assert json.loads((state_dir / "start.json").read_text()) == {"journal_records": 50, "state_file": None}
    with global_map_subscription(node, joiner.topic("global_map")) as latest:
        joiner.play(node, records[:30])  # the front-end starts again: sequence numbers from 1
        wait_for_global_map(node, joiner.topic("global_map"), lambda m: m.n_submaps == 30, 120.0, joiner, latest=latest)
    code, output = joiner.stop()
    assert code == 0, output[-3000:]
    snapshots = sorted((state_dir / "snapshots").glob("state_*.npz"), key=lambda p: int(p.stem.split("_")[1]))
    assert snapshots[-1].name == "state_80.npz"  # the clean stop's: 50 records before the reset, 30 after
    assert all(int(p.stem.split("_")[1]) >= 50 for p in snapshots)  # the new map's only: the old map's are gone
    for path in snapshots:  # none usable: recovery falls back as far as it can
        path.write_bytes(b"damaged")
    joiner = start_joiner(**params)
    final, _ = wait_for_global_map(node, joiner.topic("global_map"), lambda m: m.n_submaps == 30, 120.0, joiner)
    code, output = joiner.stop()
    assert code == 0, output[-3000:]
    assert "resumed from an empty map and 30 journal record(s)" in output, output[-3000:]
    _assert_equals_offline(final, maps[:30], mode)


@pytest.mark.parametrize("how", ["initial_map", "load_map"])
def test_save_stop_load_continue_equals_one_run(how, node, start_joiner, read_benchmark, tmp_path):
    name, mode = "VicPark_200_local_maps", "online-dc"
    maps = read_benchmark(name).maps
    records = list(read_messages(_bag(name)))
    saved = tmp_path / "saved"
    joiner, _ = _run_to_end(node, start_joiner, records[:90], 90, mode=mode, save_directory=str(saved))
    response = call_trigger(node, f"/{joiner.namespace}/joiner/save_map")
    assert response.success, response.message
    assert joiner.stop()[0] == 0
    assert (saved / "state.npz").is_file()

    if how == "initial_map":
        joiner = start_joiner(mode=mode, initial_map=str(saved / "state.npz"), publish_rate=10.0)
    else:
        joiner = start_joiner(mode=mode, load_path=str(saved / "state.npz"), publish_rate=10.0)
        response = call_trigger(node, f"/{joiner.namespace}/joiner/load_map")
        assert response.success, response.message
    loaded, _ = wait_for_global_map(node, joiner.topic("global_map"), lambda m: m.n_submaps == 90, 60.0, joiner)
    joiner.play(node, records)  # the first 90 again (skipped), then the rest
    final, _ = wait_for_global_map(node, joiner.topic("global_map"), lambda m: m.n_submaps == len(maps), 300.0, joiner)
    code, output = joiner.stop()
    assert code == 0, output[-3000:]
    assert loaded.n_submaps == 90
    _assert_equals_offline(final, maps, mode)


def test_an_unreadable_initial_map_stops_the_node(start_joiner, tmp_path):
    bad = tmp_path / "state.npz"
    bad.write_bytes(b"not a state file")
    joiner = start_joiner(initial_map=str(bad))
    code = joiner.process.wait(timeout=60)
    _, output = joiner.stop()
    assert code == 2, output
    assert f"state file {bad} cannot be read" in output
