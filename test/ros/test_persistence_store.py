"""The state directory without DDS: recovery from snapshot + journal, and every fallback it takes."""

from __future__ import annotations

import threading

import numpy as np
import pytest

from linear_slam_ros.core.errors import ConfigError
from linear_slam_ros.evaluation.synthetic import make_world, noisy_local_maps
from linear_slam_ros.joiner.joiner import Joiner, global_result
from linear_slam_ros.joiner.snapshot import blob_names, read_snapshot
from linear_slam_ros.ros.journal import read_journal
from linear_slam_ros.ros.persistence import SNAPSHOTS_KEPT, StateStore
from msg_adapters import decode_map, encode_map
from msg_adapters.bags import bag_parts, deserialize, serialize


@pytest.fixture(scope="module")
def messages():
    world = make_world(2, 40, 30, np.random.default_rng(7))
    maps = noisy_local_maps(world, np.random.default_rng(8), steps_per_map=3, sensor_range=7.0)
    return [serialize(encode_map(m, seq)) for seq, m in enumerate(maps, start=1)]


def _offer_to(joiner):
    def offer(topic: str, raw: bytes, index: int = 0) -> None:
        decoded = decode_map(*bag_parts(deserialize(raw)))
        joiner.offer(decoded.local_map, decoded.seq)

    return offer


def _session(folder, messages, snapshot_every, mode="online-dc", blob_min_bytes=None):
    """What the node does: journal each message, offer it, snapshot every ``snapshot_every``; no clean close."""
    store = StateStore(folder) if blob_min_bytes is None else StateStore(folder, blob_min_bytes)
    joiner = Joiner(mode)
    recovery = store.recover(joiner, _offer_to(joiner))
    journal = store.open_journal(recovery.journal_records)  # as the node opens it
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


def test_records_after_a_damaged_earlier_file_keep_their_indices(messages, tmp_path):
    """Records lost in the middle of the journal do not renumber the later ones: a snapshot's count still says
    which records it includes, and the next session numbers on after the last record."""
    _session(tmp_path, messages[:6], snapshot_every=3)  # journal_0: records 0-5; state_3, state_6
    _session(tmp_path, messages[6:9], snapshot_every=3)  # journal_1: records 6-8; state_9 (state_6 kept)
    journal_0 = tmp_path / "journal" / "journal_0.mcap"
    assert [r.index for r in read_journal(tmp_path / "journal").records] == list(range(9))
    data = journal_0.read_bytes()
    record_4 = data.find(messages[4])  # records 4 and 5 (and the file's closing summary) lost: a damaged disk
    journal_0.write_bytes(data[: record_4 - 40])
    newest = tmp_path / "snapshots" / "state_9.npz"
    newest.write_bytes(b"garbage")  # and the newest snapshot: state_6 and the records from 6 on are used
    joiner = Joiner("online-dc")
    store = StateStore(tmp_path)
    recovery = store.recover(joiner, _offer_to(joiner))
    assert recovery.snapshot.name == "state_6.npz" and recovery.replayed == 3 and recovery.journal_records == 9
    assert joiner.state.n_joined == 9
    assert global_result(joiner.state).x.tobytes() == global_result(_reference(messages[:9]).state).x.tobytes()
    assert any("journal_1.mcap: records" in p and "missing before record 6" in p for p in recovery.problems)
    with store.open_journal(recovery.journal_records) as journal:
        assert journal.next_index == 9


def test_a_reset_is_never_undone_by_recovery(messages, tmp_path):
    """``mark_start`` before a reset: with its snapshot lost, recovery replays only what came after the reset."""
    store = StateStore(tmp_path)
    joiner = _session(tmp_path, messages[:6], snapshot_every=3)  # records 0-5, state_3 and state_6: the old map
    store.mark_start(6)
    assert store.snapshots() == []  # the old map's snapshots are gone
    joiner.reset()
    journal = store.open_journal(6)
    for raw in messages[:4]:  # the new map: its sequence numbers start again at 1
        journal.append("local_map", raw, 0)
        _offer_to(joiner)("local_map", raw)
    journal.flush(fsync=True)
    store.write_snapshot(joiner.save(10))
    journal.close()
    (tmp_path / "snapshots" / "state_10.npz").write_bytes(b"garbage")  # the new map's snapshot is lost
    recovered = Joiner("online-dc")
    recovery = StateStore(tmp_path).recover(recovered, _offer_to(recovered))
    assert (recovery.snapshot, recovery.snapshot_records, recovery.replayed, recovery.journal_records) == (None, 6, 4, 10)
    assert recovered.n_skipped == 0 and recovered.state.n_joined == 4
    assert global_result(recovered.state).x.tobytes() == global_result(_reference(messages[:4]).state).x.tobytes()


@pytest.mark.parametrize("killed", ["at the first snapshot deleted", "once start.json is replaced"])
def test_a_reset_killed_half_way_recovers_the_old_map_or_the_new_one_never_a_mix(messages, tmp_path, monkeypatch, killed):
    """The old map's newest snapshot sits at the reset's journal count: left on disk after start.json, recovery took
    it for the new map's (6 submaps under a map that starts empty, whose seq 1 was then skipped)."""
    import os
    from pathlib import Path

    import linear_slam_ros.ros.persistence as persistence

    class Killed(BaseException):
        pass

    joiner = _session(tmp_path, messages[:6], snapshot_every=3)
    StateStore(tmp_path).write_snapshot(joiner.save(6))  # the clean stop's snapshot: at the reset's count
    unlink, replace = Path.unlink, os.replace

    def dying_unlink(path: Path, missing_ok: bool = False) -> None:
        if path.name.startswith("state_"):
            raise Killed
        unlink(path, missing_ok=missing_ok)

    def dying_replace(src: object, dst: object) -> None:
        replace(src, dst)
        raise Killed

    if killed == "at the first snapshot deleted":
        monkeypatch.setattr(Path, "unlink", dying_unlink)
    else:
        monkeypatch.setattr(persistence.os, "replace", dying_replace)
    with pytest.raises(Killed):
        StateStore(tmp_path).mark_start(6)
    monkeypatch.undo()
    recovered = Joiner("online-dc")
    StateStore(tmp_path).recover(recovered, _offer_to(recovered))
    if killed == "at the first snapshot deleted":  # the reset did not happen: the old map, exactly
        assert global_result(recovered.state).x.tobytes() == global_result(joiner.state).x.tobytes()
    else:  # the reset happened: the new map starts empty and takes seq 1
        assert recovered.state.n_joined == 0
        _offer_to(recovered)("local_map", messages[0])
        assert recovered.n_skipped == 0 and recovered.state.n_joined == 1


def test_half_written_snapshots_are_removed_on_failure_and_at_recovery(messages, tmp_path, monkeypatch):
    """A full disk or a kill left `.state_N.npz.tmp` files for good, eating the space the journal needs."""
    import errno

    import linear_slam_ros.joiner.snapshot as snapshot
    from linear_slam_ros.joiner.snapshot import SnapshotError

    joiner = _session(tmp_path, messages[:3], snapshot_every=3)
    store = StateStore(tmp_path)

    def full(fh, **_arrays) -> None:
        fh.write(b"PK" + bytes(100))
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(snapshot.np, "savez", full)
    with pytest.raises(SnapshotError, match="state_4.npz: .*No space left on device"):
        store.write_snapshot(joiner.save(4))
    monkeypatch.undo()
    assert [p.name for p in (tmp_path / "snapshots").iterdir() if p.is_file()] == ["state_3.npz"]
    killed = [tmp_path / "snapshots" / ".state_5.npz.tmp", tmp_path / "snapshots" / "blobs" / ".abc.npz.tmp"]
    for path in killed:
        path.parent.mkdir(exist_ok=True)
        path.write_bytes(b"PK")
    recovered = Joiner("online-dc")
    StateStore(tmp_path).recover(recovered, _offer_to(recovered))
    assert not any(p.exists() for p in killed) and recovered.state.n_joined == 3


def test_a_loaded_state_file_is_where_recovery_starts(messages, tmp_path):
    """``mark_start`` with the loaded file: with no usable snapshot of the new map, the file is read again."""
    from linear_slam_ros.joiner.snapshot import write_snapshot

    loaded = tmp_path / "saved.npz"
    write_snapshot(loaded, _reference(messages[:5]).save())
    state_dir = tmp_path / "state"
    _session(state_dir, messages[:3], snapshot_every=2)  # an old map: records 0-2, state_2
    store = StateStore(state_dir)
    store.mark_start(3, loaded)
    joiner = Joiner("online-dc")
    joiner.restore(read_snapshot(loaded))
    journal = store.open_journal(3)
    for raw in messages[5:7]:
        journal.append("local_map", raw, 0)
        _offer_to(joiner)("local_map", raw)
    journal.close()  # a kill before the snapshot of the loaded map: none on disk
    recovered = Joiner("online-dc")
    recovery = StateStore(state_dir).recover(recovered, _offer_to(recovered))
    assert recovery.snapshot == loaded.resolve() and (recovery.replayed, recovery.journal_records) == (2, 5)
    assert global_result(recovered.state).x.tobytes() == global_result(joiner.state).x.tobytes()
    loaded.unlink()  # and without it: said, and the map starts empty at the load
    recovered = Joiner("online-dc")
    recovery = StateStore(state_dir).recover(recovered, _offer_to(recovered))
    assert any("the map it started from is lost, starting empty at journal record 3" in p for p in recovery.problems)
    assert recovery.snapshot is None and recovered.state.n_joined == 0  # messages 6, 7 wait for 1-5 (reorder)
    (state_dir / "start.json").write_text("{not json")
    recovered = Joiner("online-dc")
    recovery = StateStore(state_dir).recover(recovered, _offer_to(recovered))
    assert any("start.json cannot be read" in p and "from the whole journal" in p for p in recovery.problems)


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


def test_a_journal_without_its_metadata_is_state_all_the_same(messages, tmp_path):
    """Without journal/metadata.yaml (lost, or removed by hand) and no snapshot, the folder counted as empty: the start
    began an empty map, whose first snapshot then brought the old journal back at the next start."""
    _session(tmp_path, messages[:10], snapshot_every=1000)
    (tmp_path / "journal" / "metadata.yaml").unlink()
    store = StateStore(tmp_path)
    assert store.has_state() and not store.snapshots()
    joiner = Joiner("online-dc")
    assert store.recover(joiner, _offer_to(joiner)).replayed == 10 and joiner.state.n_joined == 10
