"""The state directory without DDS: recovery from snapshot + journal, and every fallback it takes."""

from __future__ import annotations

import threading

import numpy as np
import pytest

from linear_slam_ros.core.errors import ConfigError
from linear_slam_ros.evaluation.synthetic import make_world, noisy_local_maps
from linear_slam_ros.joiner.joiner import Joiner, global_result
from linear_slam_ros.joiner.snapshot import blob_names, read_snapshot
from linear_slam_ros.ros.persistence import SNAPSHOTS_KEPT, StateStore
from msg_adapters import decode_map, encode_map
from msg_adapters.bags import bag_parts, deserialize, serialize


@pytest.fixture(scope="module")
def messages():
    world = make_world(2, 40, 30, np.random.default_rng(7))
    maps = noisy_local_maps(world, np.random.default_rng(8), steps_per_map=3, sensor_range=7.0)
    return [serialize(encode_map(m, seq)) for seq, m in enumerate(maps, start=1)]


def _offer_to(joiner):
    def offer(topic: str, raw: bytes) -> None:
        decoded = decode_map(*bag_parts(deserialize(raw)))
        joiner.offer(decoded.local_map, decoded.seq)

    return offer


def _session(folder, messages, snapshot_every, mode="online-dc", blob_min_bytes=None):
    """What the node does: journal each message, offer it, snapshot every ``snapshot_every``; no clean close."""
    store = StateStore(folder) if blob_min_bytes is None else StateStore(folder, blob_min_bytes)
    joiner = Joiner(mode)
    store.recover(joiner, _offer_to(joiner))
    journal = store.open_journal()
    offer = _offer_to(joiner)
    for raw in messages:
        index = journal.append("local_map", raw, 0)
        offer("local_map", raw)
        if (index + 1) % snapshot_every == 0:
            journal.flush(fsync=True)
            store.write_snapshot(joiner.save(index + 1))
    journal.flush(fsync=False)  # a kill -9 here: no close, no final snapshot
    return joiner


def _reference(messages, mode="online-dc"):
    joiner = Joiner(mode)
    offer = _offer_to(joiner)
    for raw in messages:
        offer("local_map", raw)
    return joiner


def test_recovery_restores_the_newest_snapshot_and_replays_the_rest(messages, tmp_path):
    _session(tmp_path, messages[:7], snapshot_every=3)
    store = StateStore(tmp_path)
    assert [n for n, _ in store.snapshots()] == [6, 3]  # two kept, newest first
    assert len(store.snapshots()) == SNAPSHOTS_KEPT
    joiner = Joiner("online-dc")
    recovery = store.recover(joiner, _offer_to(joiner))
    assert recovery.snapshot is not None and recovery.snapshot.name == "state_6.npz"
    assert (recovery.snapshot_records, recovery.replayed, recovery.problems) == (6, 1, ())
    for raw in messages:  # the whole stream again, as a replayed bag: 7 skipped, the rest joined
        _offer_to(joiner)("local_map", raw)
    reference = _reference(messages)
    assert joiner.n_skipped == 7 and joiner.n_rejected == 0
    assert global_result(joiner.state).x.tobytes() == global_result(reference.state).x.tobytes()


def test_a_corrupt_newest_snapshot_falls_back_to_the_older_one(messages, tmp_path):
    _session(tmp_path, messages[:7], snapshot_every=3)
    newest = tmp_path / "snapshots" / "state_6.npz"
    newest.write_bytes(newest.read_bytes()[:-100])
    joiner = Joiner("online-dc")
    recovery = StateStore(tmp_path).recover(joiner, _offer_to(joiner))
    assert recovery.snapshot.name == "state_3.npz" and recovery.replayed == 4
    assert any("state_6.npz" in p and "falling back to an older point" in p for p in recovery.problems)
    assert joiner.state.n_joined == 7


def test_no_usable_snapshot_replays_the_whole_journal(messages, tmp_path):
    _session(tmp_path, messages[:5], snapshot_every=2)
    for _, path in StateStore(tmp_path).snapshots():
        path.write_bytes(b"garbage")
    joiner = Joiner("online-dc")
    recovery = StateStore(tmp_path).recover(joiner, _offer_to(joiner))
    assert recovery.snapshot is None and recovery.replayed == 5 and len(recovery.problems) == 2
    assert global_result(joiner.state).x.tobytes() == global_result(_reference(messages[:5]).state).x.tobytes()


def test_a_truncated_journal_tail_is_reported_and_dropped(messages, tmp_path):
    _session(tmp_path, messages[:4], snapshot_every=100)
    journal_file = next((tmp_path / "journal").glob("journal_*.mcap"))
    # a copy cut short inside the last record (the zero bytes the live file reserves after it dropped too)
    journal_file.write_bytes(journal_file.read_bytes().rstrip(b"\0")[:-5])
    joiner = Joiner("online-dc")
    recovery = StateStore(tmp_path).recover(joiner, _offer_to(joiner))
    assert recovery.replayed == 3 and any("journal_0.mcap" in p for p in recovery.problems)
    assert joiner.state.n_joined == 3


def test_sessions_append_and_the_journal_stays_one_bag(messages, tmp_path):
    _session(tmp_path, messages[:3], snapshot_every=100)
    joiner = _session(tmp_path, messages, snapshot_every=100)  # resumes, then gets the whole stream again
    assert joiner.state.n_joined == len(messages) and joiner.n_skipped == 3
    assert sorted(p.name for p in (tmp_path / "journal").glob("*.mcap")) == ["journal_0.mcap", "journal_1.mcap"]


def test_a_snapshot_of_another_mode_refuses_to_start(messages, tmp_path):
    _session(tmp_path, messages[:3], snapshot_every=3, mode="sequential")
    joiner = Joiner("online-dc")
    with pytest.raises(ConfigError, match="the saved map was joined with mode='sequential'"):
        StateStore(tmp_path).recover(joiner, _offer_to(joiner))


def test_snapshots_write_each_large_map_once_and_delete_the_blobs_no_kept_snapshot_names(messages, tmp_path):
    _session(tmp_path, messages[:14], snapshot_every=3, blob_min_bytes=0)  # snapshots at 3, 6, 9, 12
    store = StateStore(tmp_path)
    assert [n for n, _ in store.snapshots()] == [12, 9]
    named = set().union(*(blob_names(path) for _, path in store.snapshots()))
    assert {p.name for p in store.blobs.folder.iterdir()} == {f"{n}.npz" for n in named}
    assert blob_names(tmp_path / "snapshots" / "state_12.npz") & blob_names(tmp_path / "snapshots" / "state_9.npz")
    joiner = Joiner("online-dc")
    recovery = store.recover(joiner, _offer_to(joiner))
    assert (recovery.snapshot.name, recovery.replayed, recovery.problems) == ("state_12.npz", 2, ())
    assert global_result(joiner.state).x.tobytes() == global_result(_reference(messages[:14]).state).x.tobytes()


def test_a_corrupt_blob_falls_back_to_an_older_point(messages, tmp_path):
    _session(tmp_path, messages[:7], snapshot_every=3, blob_min_bytes=0)
    newest = tmp_path / "snapshots" / "state_6.npz"
    only_newest = blob_names(newest) - blob_names(tmp_path / "snapshots" / "state_3.npz")
    blob = StateStore(tmp_path).blobs.path(sorted(only_newest)[0])
    blob.write_bytes(blob.read_bytes()[:-100])
    joiner = Joiner("online-dc")
    recovery = StateStore(tmp_path).recover(joiner, _offer_to(joiner))
    assert recovery.snapshot.name == "state_3.npz" and recovery.replayed == 4
    assert any(blob.name in p and "falling back to an older point" in p for p in recovery.problems)
    assert global_result(joiner.state).x.tobytes() == global_result(_reference(messages[:7]).state).x.tobytes()


def test_blobs_stay_when_a_kept_snapshot_cannot_be_read(messages, tmp_path, caplog):
    _session(tmp_path, messages[:7], snapshot_every=3, blob_min_bytes=0)  # state_6, state_3
    store = StateStore(tmp_path, blob_min_bytes=0)
    six = tmp_path / "snapshots" / "state_6.npz"
    before = {p.name for p in store.blobs.folder.iterdir()}
    six.write_bytes(b"garbage")
    joiner = _reference(messages[:9])
    names = blob_names(store.write_snapshot(joiner.save(9)))  # keeps state_9 and the unreadable state_6
    after = {p.name for p in store.blobs.folder.iterdir()}
    assert before <= after and {f"{n}.npz" for n in names} <= after  # nothing deleted this time
    assert "unused blobs of" in caplog.text and "left in place this time" in caplog.text


def test_two_snapshots_at_once_are_written_one_after_the_other(messages, tmp_path):
    store = StateStore(tmp_path, blob_min_bytes=0)
    first, second = _reference(messages[:6]), _reference(messages[:9])
    entered, release = threading.Event(), threading.Event()
    real_sync = store.blobs.sync

    def slow_sync():
        entered.set()
        assert release.wait(30.0)
        real_sync()

    store.blobs.sync = slow_sync
    a = threading.Thread(target=store.write_snapshot, args=(first.save(6),))
    a.start()
    assert entered.wait(30.0)
    store.blobs.sync = real_sync
    b = threading.Thread(target=store.write_snapshot, args=(second.save(9),))
    b.start()
    b.join(timeout=0.5)
    assert b.is_alive() and not (tmp_path / "snapshots" / "state_9.npz").exists()  # waits for the first
    release.set()
    a.join(timeout=30.0)
    b.join(timeout=30.0)
    for n, joiner in ((6, first), (9, second)):
        restored = read_snapshot(tmp_path / "snapshots" / f"state_{n}.npz")
        assert global_result(restored.state).x.tobytes() == global_result(joiner.state).x.tobytes()
