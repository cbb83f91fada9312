"""The crash-safe journal (linear_slam_ros.ros.journal): round trips, truncation at every byte, fsync policy.

No DDS: these tests only write and read files (they live under test/ros because only ros/ may
import rosbags and mcap).
"""

from __future__ import annotations

import os
import re
import shutil
from pathlib import Path

import numpy as np
import pytest
from mcap.writer import CompressionType, IndexType, Writer
from rosbags.rosbag2 import Reader
from ruamel.yaml import YAML

from linear_slam_ros.ros import journal as journal_module
from linear_slam_ros.ros.bagio import read_messages, write_messages
from linear_slam_ros.ros.journal import (
    METADATA_NAME,
    Journal,
    JournalContents,
    JournalError,
    JournalRecord,
    read_journal,
)
from msg_adapters.bags import MSGTYPE, TYPESTORE, serialize
from msg_adapters.layout import Encoded

T0 = 1_700_000_000 * 10**9
TOPICS = ("local_map", "pose_graph")


def _messages(seed: int, n: int, max_values: int = 40) -> list[tuple[str, bytes, int]]:
    """Return ``n`` seeded ``(topic, CDR bytes, time ns)`` messages of varying sizes.

    Records 0 and 1 are on ``local_map`` and ``pose_graph``, so from record 2 on no record is
    preceded by a channel record: a record's bytes then run from one file size to the next.
    """
    rng = np.random.default_rng(seed)
    out = []
    for i in range(n):
        k = int(rng.integers(0, max_values))
        raw = serialize(Encoded.of(("header", "data"), (3, k), rng.standard_normal(3 + k)))
        topic = TOPICS[i] if i < 2 else TOPICS[int(rng.integers(0, 2))]  # both channels before record 2
        out.append((topic, raw, T0 + i * 100_000_000))
    return out


def _expected(messages: list[tuple[str, bytes, int]], start: int = 0) -> list[JournalRecord]:
    return [JournalRecord(start + i, topic, raw, t) for i, (topic, raw, t) in enumerate(messages)]


def _write_session(folder: Path, messages: list[tuple[str, bytes, int]], close: bool = True) -> tuple[Journal, list[int]]:
    """Append ``messages`` in a new session; return the journal and the bytes written after open and after each record."""
    journal = Journal.open(folder)
    ends = [journal.bytes_written]
    for topic, raw, t in messages:
        journal.append(topic, raw, t)
        ends.append(journal.bytes_written)  # appended records are with the OS already
    if close:
        journal.close()
    return journal, ends


def _metadata(folder: Path) -> dict:
    return YAML(typ="safe").load((folder / METADATA_NAME).read_text())["rosbag2_bagfile_information"]


def test_round_trip_across_two_sessions(tmp_path: Path) -> None:
    folder = tmp_path / "state" / "journal"
    first, second = _messages(1, 5), _messages(2, 3)
    second = [(topic, raw, t + 10**9) for topic, raw, t in second]
    with Journal.open(folder) as journal:
        assert journal.next_index == 0 and journal.path.name == "journal_0.mcap"
        assert [journal.append(*m) for m in first] == [0, 1, 2, 3, 4]
    assert journal.closed
    journal.close()  # idempotent
    with Journal.open(folder) as journal:
        assert journal.next_index == 5 and journal.path.name == "journal_1.mcap"
        assert [journal.append(*m) for m in second] == [5, 6, 7]

    contents = read_journal(folder)
    assert contents.problems == ()
    assert list(contents.records) == _expected(first + second)
    assert contents.count == 8 and contents.after(6) == contents.records[6:] and contents.after(9) == ()
    assert [(f.name, f.first_index, f.count, f.closed, f.dropped_bytes) for f in contents.files] == [
        ("journal_0.mcap", 0, 5, True, 0),
        ("journal_1.mcap", 5, 3, True, 0),
    ]

    meta = _metadata(folder)
    assert meta["version"] == 9 and meta["storage_identifier"] == "mcap" and meta["message_count"] == 8
    assert meta["relative_file_paths"] == ["journal_0.mcap", "journal_1.mcap"]
    assert [(f["path"], f["message_count"]) for f in meta["files"]] == [("journal_0.mcap", 5), ("journal_1.mcap", 3)]
    assert meta["files"][1]["starting_time"]["nanoseconds_since_epoch"] == second[0][2]
    assert meta["files"][1]["duration"]["nanoseconds"] == second[-1][2] - second[0][2]
    counts = {t["topic_metadata"]["name"]: t["message_count"] for t in meta["topics_with_message_count"]}
    assert counts == {topic: sum(m[0] == topic for m in first + second) for topic in TOPICS}
    topic_meta = meta["topics_with_message_count"][0]["topic_metadata"]
    assert topic_meta["type"] == MSGTYPE and topic_meta["serialization_format"] == "cdr"
    assert topic_meta["type_description_hash"] == TYPESTORE.hash_rihs01(MSGTYPE)
    (profile,) = topic_meta["offered_qos_profiles"]
    assert (profile["reliability"], profile["durability"], profile["history"]) == ("reliable", "volatile", "keep_all")
    assert not list(folder.glob(".*.tmp"))
    assert "&id" not in (folder / METADATA_NAME).read_text()  # no YAML aliases, as rosbags writes it

    with Reader(folder) as reader:  # rosbags reads the bag folder and both storage files
        assert reader.message_count == 8
        got = [(c.topic, t, bytes(raw)) for c, t, raw in reader.messages()]
    assert got == [(topic, t, raw) for topic, raw, t in first + second]
    assert [(r.topic, r.time_ns, r.raw, r.latched) for r in read_messages(folder)] == [
        (topic, t, raw, False) for topic, raw, t in first + second
    ]


def test_the_live_file_holds_the_records_mcaps_writer_writes(tmp_path: Path) -> None:
    """Each record a session copies into its mapped file is byte for byte what mcap's Writer writes for it,
    and a closed file is the Writer's whole output (summary and footer included)."""
    messages = _messages(12, 7)
    journal, ends = _write_session(tmp_path / "j", messages, close=False)
    live = journal.path.read_bytes()
    assert not any(live[ends[-1] :])  # then space reserved ahead
    journal.close()

    class Sink:  # what mcap's Writer writes, with the data section as it stands before finish()
        def __init__(self) -> None:
            self.data = bytearray()

        def write(self, b: bytes) -> int:
            self.data += b
            return len(b)

        def tell(self) -> int:
            return len(self.data)

    sink = Sink()
    writer = Writer(sink, use_chunking=False, compression=CompressionType.NONE, index_types=IndexType.ALL)
    writer.start(profile="ros2", library=journal_module._LIBRARY)
    schema = writer.register_schema(name=MSGTYPE, encoding="ros2msg", data=journal_module._MSGDEF.encode())
    writer.add_metadata("rosbag2", journal_module._rosbag2_metadata("journal_0.mcap"))
    channels: dict[str, int] = {}
    for i, (topic, raw, t) in enumerate(messages):
        if topic not in channels:
            channels[topic] = writer.register_channel(topic, "cdr", schema, dict(journal_module._CHANNEL_METADATA))
        writer.add_message(channel_id=channels[topic], log_time=t, data=raw, publish_time=t, sequence=i)
    assert live[: ends[-1]] == bytes(sink.data)
    writer.finish()
    assert (tmp_path / "j" / "journal_0.mcap").read_bytes() == bytes(sink.data)


def test_restart_after_a_kill_seals_the_file_and_continues_the_indices(tmp_path: Path) -> None:
    live = tmp_path / "live"
    messages = _messages(3, 6)
    journal, ends = _write_session(live, messages[:4], close=False)
    crashed = tmp_path / "crashed"
    shutil.copytree(live, crashed)  # the files as a kill -9 now would leave them: no footer
    journal.close()
    with open(crashed / "journal_0.mcap", "r+b") as f:
        f.truncate(ends[4] - 5)  # ... and record 3 cut short
    contents = read_journal(crashed)
    assert list(contents.records) == _expected(messages[:3])
    assert contents.problems == (f"journal_0.mcap: truncated after record 2 ({ends[4] - 5 - ends[3]} bytes dropped)",)

    with Journal.open(crashed) as resumed:
        assert resumed.next_index == 3 and resumed.path.name == "journal_1.mcap"
        assert resumed.append(*messages[4]) == 3
        resumed.flush(fsync=False)
        assert _metadata(crashed)["files"][0]["message_count"] == 3  # exact again
        assert _metadata(crashed)["files"][1]["message_count"] == 1
    contents = read_journal(crashed)
    assert contents.problems == ()
    assert list(contents.records) == _expected(messages[:3] + messages[4:5])
    assert [r.raw for r in read_messages(crashed)] == [m[1] for m in messages[:3] + messages[4:5]]


def test_a_cut_at_any_byte_drops_only_the_incomplete_record(tmp_path: Path) -> None:
    folder = tmp_path / "journal"
    small = serialize(Encoded.of(("header",), (3,), np.arange(3.0)))  # a short last record: fewer cuts to read
    messages = [*_messages(4, 5), ("pose_graph", small, T0 + 10**9)]
    _, ends = _write_session(folder, messages)
    whole = (folder / "journal_0.mcap").read_bytes()
    n = len(messages)
    cuts = [
        *range(0, 10),  # in the magic and the header record's opcode and length
        *range(10, ends[0] + 1, 37),  # in the header, schema, metadata record
        *range(ends[2] + 1, ends[3], 11),  # in record 2 (a middle one)
        *range(ends[n - 1], ends[n] + 1),  # at every byte of the last record
        *range(ends[n] + 1, len(whole) - 8, 29),  # in the closing summary (DataEnd, schema, channels, statistics, ...)
        *range(len(whole) - 8, len(whole) + 1),  # in the footer's closing magic
    ]
    for cut in cuts:
        (folder / "journal_0.mcap").write_bytes(whole[:cut])
        contents = read_journal(folder)  # never raises
        complete = sum(1 for e in ends[1:] if e <= cut)
        assert list(contents.records) == _expected(messages[:complete]), cut
        if cut == 0 or cut in ends or cut > ends[-1]:  # between records, or in the closing summary: nothing lost
            assert contents.problems == (), (cut, contents.problems)
        elif complete:
            dropped = cut - ends[complete]
            assert contents.problems == (f"journal_0.mcap: truncated after record {complete - 1} ({dropped} bytes dropped)",), cut
        else:  # in (or between) the header, schema and metadata records
            assert contents.problems == () or re.fullmatch(
                r"journal_0\.mcap: truncated before its first record \(\d+ bytes dropped\)", contents.problems[0]
            ), (cut, contents.problems)
        assert contents.files[0].closed == (cut == len(whole))
        assert contents.files[0].count == complete


def test_journal_open_after_a_cut_continues_from_the_complete_records(tmp_path: Path) -> None:
    messages = _messages(5, 4)
    _, ends = _write_session(tmp_path / "j", messages)
    whole = (tmp_path / "j" / "journal_0.mcap").read_bytes()
    for cut in (0, 5, ends[0], ends[1] + 1, ends[3] - 1, ends[4], len(whole) - 3):
        folder = tmp_path / f"cut{cut}"
        shutil.copytree(tmp_path / "j", folder)
        (folder / "journal_0.mcap").write_bytes(whole[:cut])
        complete = sum(1 for e in ends[1:] if e <= cut)
        with Journal.open(folder) as journal:
            assert journal.next_index == complete
            assert journal.append("local_map", b"\x00\x01\x00\x00", T0 + 10**10) == complete
        contents = read_journal(folder)
        assert contents.problems == (), cut
        assert [r.raw for r in contents.records] == [m[1] for m in messages[:complete]] + [b"\x00\x01\x00\x00"]
        assert len(list(read_messages(folder))) == complete + 1


def test_a_truncated_earlier_file_is_tolerated_and_reported(tmp_path: Path) -> None:
    folder = tmp_path / "journal"
    first, second = _messages(6, 4), _messages(7, 2)
    _, ends = _write_session(folder, first)
    _write_session(folder, second)
    with open(folder / "journal_0.mcap", "r+b") as f:
        f.truncate(ends[3] + 10)  # record 3 and the closing summary lost (e.g. a damaged disk)
    contents = read_journal(folder)
    assert [r.raw for r in contents.records] == [m[1] for m in first[:3] + second]
    assert [r.index for r in contents.records] == [0, 1, 2, 4, 5]  # as appended: a snapshot's count still holds
    assert contents.problems == (
        "journal_0.mcap: truncated after record 2 (10 bytes dropped)",
        "journal_1.mcap: record 3 missing before record 4",
    )
    assert contents.count == 6 and [r.index for r in contents.after(3)] == [4, 5] and contents.after(6) == ()
    assert [(f.first_index, f.count) for f in contents.files] == [(0, 3), (4, 2)]
    with Journal.open(folder) as journal:  # the next session numbers on from the last record, not from the count read
        assert journal.next_index == 6 and journal.append(*first[0]) == 6
    with Journal.open(folder, first_index=9) as journal:  # a snapshot that includes more than the journal holds
        assert journal.append(*first[1]) == 9
    assert [r.index for r in read_journal(folder).records] == [0, 1, 2, 4, 5, 6, 9]


def test_a_zero_tail_is_reserved_space_and_a_damaged_tail_is_kept_aside(tmp_path: Path) -> None:
    messages = _messages(8, 3)
    journal, ends = _write_session(tmp_path / "live", messages, close=False)
    folder = tmp_path / "crashed"
    shutil.copytree(tmp_path / "live", folder)  # as a kill -9 leaves it: no footer, reserved zero bytes after the records
    journal.close()
    path = folder / "journal_0.mcap"
    size = path.stat().st_size
    assert size > ends[-1] and not any(path.read_bytes()[ends[-1] :])
    contents = read_journal(folder)
    assert [r.raw for r in contents.records] == [m[1] for m in messages]
    assert contents.problems == ()  # a crash between records loses nothing
    assert [(f.closed, f.dropped_bytes) for f in contents.files] == [(False, 0)]

    with open(path, "r+b") as f:
        f.seek(ends[-1] + 4096)
        f.write(b"\x05" + bytes(8) + b"stale")  # bytes after a page that a power cut lost
    contents = read_journal(folder)
    assert [r.raw for r in contents.records] == [m[1] for m in messages]
    dropped = size - ends[-1]
    damaged = f"journal_0.mcap: damaged (invalid record (opcode 0x00)) after record 2 ({dropped} bytes dropped)"
    assert contents.problems == (damaged,)
    with Journal.open(folder) as resumed:
        assert resumed.next_index == 3
    assert (folder / "journal_0.mcap.damaged").stat().st_size == size
    assert read_journal(folder).problems == ()
    assert path.stat().st_size < ends[-1] + 4096  # sealed: the records, the summary and the footer, nothing reserved


def test_a_kill_during_any_byte_of_a_mapped_write_drops_only_that_record(tmp_path: Path) -> None:
    """The storage file is written through a memory map: bytes 1-8 (the record's length), then its body, then
    its opcode byte. A kill at any instant leaves the bytes copied so far and zeros after them."""
    folder = tmp_path / "journal"
    small = serialize(Encoded.of(("header",), (3,), np.arange(3.0)))
    messages = [*_messages(11, 4), ("pose_graph", small, T0 + 10**9)]
    journal, ends = _write_session(folder, messages, close=False)
    live = journal.path.read_bytes()
    journal.close()
    start, stop = ends[-2], ends[-1]
    body = live[start + 1 : stop]
    for copied in range(len(body) + 1):  # bytes of the record after its opcode that reached the map
        image = bytearray(live)
        image[start:] = bytes(len(live) - start)
        image[start + 1 : start + 1 + copied] = body[:copied]
        (folder / "journal_0.mcap").write_bytes(bytes(image))
        contents = read_journal(folder)
        assert list(contents.records) == _expected(messages[:-1]), copied
        if copied:
            nonzero = len(bytes(image).rstrip(b"\0")) - start
            assert contents.problems == (
                f"journal_0.mcap: truncated after record {len(messages) - 2} ({nonzero} bytes dropped)",
            ), copied
        else:
            assert contents.problems == (), copied
    image[start] = live[start]  # the opcode, last: the record is complete
    (folder / "journal_0.mcap").write_bytes(bytes(image))
    assert list(read_journal(folder).records) == _expected(messages)
    with Journal.open(folder) as resumed:
        assert resumed.next_index == len(messages)
    assert [r.raw for r in read_messages(folder)] == [m[1] for m in messages]


def test_files_listed_but_missing_or_not_mcap_are_reported(tmp_path: Path) -> None:
    folder = tmp_path / "journal"
    _write_session(folder, _messages(9, 2))
    _write_session(folder, _messages(10, 2))
    (folder / "journal_0.mcap").unlink()
    contents = read_journal(folder)
    assert [r.index for r in contents.records] == [2, 3]
    assert contents.problems[0].startswith("journal_0.mcap: listed in metadata.yaml but missing")
    assert contents.problems[1] == "journal_1.mcap: records 0 to 1 missing before record 2"

    (folder / "journal_2.mcap").write_bytes(b"not an mcap file at all")
    assert "journal_2.mcap: not an MCAP file" in read_journal(folder).problems[-1]
    with pytest.raises(JournalError, match=r"journal_2\.mcap: not a readable MCAP storage file"):
        Journal.open(folder)


def test_a_folder_that_is_not_a_journal_raises(tmp_path: Path) -> None:
    with pytest.raises(JournalError, match=r"missing.*not a journal: no such folder"):
        read_journal(tmp_path / "missing")
    (tmp_path / "file").write_text("x")
    with pytest.raises(JournalError, match=r"file: not a journal: not a folder"):
        read_journal(tmp_path / "file")
    other = tmp_path / "other"
    other.mkdir()
    (other / "notes.txt").write_text("hello")
    with pytest.raises(JournalError, match=r"other: not a journal: no metadata\.yaml and no journal_<k>\.mcap files"):
        read_journal(other)
    with pytest.raises(JournalError, match=r"other: not a journal"):
        Journal.open(other)
    assert sorted(p.name for p in other.iterdir()) == ["notes.txt"]  # refused before writing anything
    bag = tmp_path / "bag"
    write_messages(bag, [("local_map", T0, b"\x00\x01\x00\x00")])
    with pytest.raises(JournalError, match=r"bag: not a journal: its metadata\.yaml lists 'bag\.mcap'"):
        read_journal(bag)
    (other / METADATA_NAME).write_text("just: text\n")
    with pytest.raises(JournalError, match=r"other: not a journal: metadata\.yaml is not rosbag2 metadata"):
        read_journal(other)
    empty = tmp_path / "empty"
    empty.mkdir()
    assert read_journal(empty) == JournalContents(empty, (), (), ())


def test_the_mapped_file_grows_and_a_full_disk_stops_appends_cleanly(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(journal_module, "MAPPED_INITIAL_BYTES", 4096)
    monkeypatch.setattr(journal_module, "MAPPED_GROWTH_MAX_BYTES", 8192)
    messages = _messages(13, 60, max_values=200)  # about 50 kB: the file grows 4 -> 8 -> 16 -> 24 ... kB
    journal, ends = _write_session(tmp_path / "j", messages, close=False)
    assert journal.path.stat().st_size >= ends[-1] > 4 * 8192
    journal.close()
    assert list(read_journal(tmp_path / "j").records) == _expected(messages)
    assert (tmp_path / "j" / "journal_0.mcap").stat().st_size > ends[-1]  # the summary and footer, nothing reserved

    def no_space(fd: int, offset: int, length: int) -> None:
        raise OSError(28, "No space left on device")

    journal = Journal.open(tmp_path / "j")
    journal.append(*messages[0])  # in the space reserved at open
    monkeypatch.setattr(os, "posix_fallocate", no_space)
    with pytest.raises(JournalError, match=r"cannot append to .*journal_1\.mcap: \[Errno 28\] No space left on device"):
        for m in messages:
            journal.append(*m)
    with pytest.raises(JournalError, match=r"failed \(OSError: .*No space left on device\): restart to continue"):
        journal.append(*messages[0])
    journal.close()  # a failed journal closes without writing
    monkeypatch.undo()
    contents = read_journal(tmp_path / "j")
    appended = contents.count - len(messages)
    assert appended >= 1 and contents.problems == ()
    assert [r.raw for r in contents.records[len(messages) :]] == [m[1] for m in [messages[0], *messages[: appended - 1]]]


def test_fsync_policy(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    real_fsync = os.fsync
    calls: list[int] = []

    def counting_fsync(fd: int) -> None:
        calls.append(fd)
        real_fsync(fd)

    monkeypatch.setattr(os, "fsync", counting_fsync)
    now = [100.0]
    journal = Journal.open(tmp_path / "j", fsync_every=3, fsync_period_s=1.0, clock=lambda: now[0])
    assert calls  # the new file, metadata.yaml and the folder are durable once open returns
    calls.clear()
    for i in range(7):
        journal.append("local_map", b"\x00\x01\x00\x00", T0 + i)
    assert len(calls) == 2  # after records 3 and 6
    now[0] += 1.0
    journal.append("local_map", b"\x00\x01\x00\x00", T0 + 7)  # 2 unsynced, 1 s since the last fsync
    assert len(calls) == 3
    journal.append("local_map", b"\x00\x01\x00\x00", T0 + 8)
    assert len(calls) == 3 and not journal.maybe_sync()  # not due yet
    now[0] += 1.5
    assert journal.maybe_sync() and len(calls) == 4
    assert not journal.maybe_sync()  # nothing left to sync
    calls.clear()
    journal.flush(fsync=True)
    assert len(calls) == 3  # the storage file, metadata.yaml's temporary, the folder
    calls.clear()
    journal.flush(fsync=False)
    assert calls == []
    journal.close()
    assert calls  # close fsyncs
    calls.clear()

    quiet = Journal.open(tmp_path / "q", fsync_every=None, fsync_period_s=None, clock=lambda: now[0])
    calls.clear()
    for i in range(500):
        now[0] += 0.01
        quiet.append("pose_graph", b"\x00\x01\x00\x00", T0 + i)
    assert calls == [] and not quiet.maybe_sync()
    quiet.close()
    assert read_journal(tmp_path / "q").count == 500
    with pytest.raises(JournalError, match="fsync_every must be >= 1"):
        Journal.open(tmp_path / "x", fsync_every=0)


def test_metadata_counts_lag_until_flush(tmp_path: Path) -> None:
    folder = tmp_path / "journal"
    journal = Journal.open(folder)
    for i in range(3):
        journal.append("local_map", b"\x00\x01\x00\x00", T0 + i)
    assert _metadata(folder)["message_count"] == 0  # rewritten on open, flush and close only
    assert read_journal(folder).count == 3  # the reader counts the file itself
    journal.flush(fsync=False)
    assert _metadata(folder)["message_count"] == 3
    journal.close()


def test_times_are_made_non_decreasing_and_bad_appends_raise(tmp_path: Path) -> None:
    folder = tmp_path / "journal"
    journal = Journal.open(folder)
    journal.append("local_map", b"\x00\x01\x00\x00", T0 + 10)
    journal.append("local_map", b"\x00\x01\x00\x01", T0 + 5)  # a clock step back
    journal.append("local_map", b"\x00\x01\x00\x02", np.int64(T0 + 20))  # type: ignore[arg-type]
    with pytest.raises(JournalError, match="log_time_ns"):
        journal.append("local_map", b"", -1)
    with pytest.raises(JournalError, match="log_time_ns must be an integer"):
        journal.append("local_map", b"", 1.5)  # type: ignore[arg-type]
    with pytest.raises(JournalError, match="topic"):
        journal.append("", b"", 0)
    journal.close()
    with pytest.raises(JournalError, match="is closed"):
        journal.append("local_map", b"", T0)
    assert [r.log_time_ns for r in read_journal(folder).records] == [T0 + 10, T0 + 10, T0 + 20]
    assert [r.time_ns for r in read_messages(folder)] == [T0 + 10, T0 + 10, T0 + 20]  # rosbags needs file order = time order


def test_one_writer_at_a_time(tmp_path: Path) -> None:
    folder = tmp_path / "journal"
    journal = Journal.open(folder)
    with pytest.raises(JournalError, match=r"journal .* is in use"):
        Journal.open(folder)  # a second node on the same state_dir must not seal the live file
    assert read_journal(folder).count == 0  # reading needs no lock
    journal.close()
    with Journal.open(folder) as again:
        assert again.path.name == "journal_1.mcap"
    crashed = tmp_path / "crashed"
    crashed.mkdir()
    (crashed / ".lock").touch()  # all an interrupted first open may leave
    assert read_journal(crashed).count == 0
    with Journal.open(crashed) as journal:
        assert journal.next_index == 0


def test_indices_unwrap_the_32_bit_sequence_and_a_record_out_of_order_is_numbered_next(tmp_path: Path) -> None:
    index = journal_module._index
    assert index(0, -1) == 0 and index(7, -1) == 7  # a journal whose first records were lost
    assert index(5, 2**32 + 3) == 2**32 + 5 and index(0, 2**32 - 1) == 2**32  # past the wrap of MCAP's sequence
    assert index(3, 10) is None and index(10, 10) is None  # behind, or a repeat: cannot follow
    folder = tmp_path / "journal"
    _write_session(folder, _messages(11, 3))
    shutil.copy(folder / "journal_0.mcap", folder / "journal_1.mcap")  # sequences 0..2 again after record 2
    contents = read_journal(folder)
    assert [r.index for r in contents.records] == [0, 1, 2, 3, 4, 5]
    assert "journal_1.mcap: record 3 carries sequence 0: out of order, numbered 3" in contents.problems
