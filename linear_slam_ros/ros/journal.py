"""A crash-safe journal of the joiner's inbound messages: a rosbag2 bag folder of unchunked MCAP files.

With ``state_dir`` set, the node appends every submap message it accepts (the raw CDR bytes of a
``std_msgs/msg/Float64MultiArray`` received on ``local_map`` or ``pose_graph``) with
:meth:`Journal.append` BEFORE joining it. After a crash it restores its newest snapshot, which
records how many journal records it includes, and replays the records after that count
(:func:`read_journal`, :meth:`JournalContents.after`). A record's index is its position in the
whole journal, 0-based, in arrival order, across all storage files, as appended: the reader takes
it from the record's MCAP sequence, so records lost before it (a damaged earlier file) do not
renumber it.

On-disk layout (``<state_dir>/journal/``)::

    metadata.yaml        rosbag2 metadata, version 9, storage_identifier mcap: every storage file
                         (relative_file_paths, files: message count and time range), per-topic
                         counts, type std_msgs/msg/Float64MultiArray, type_description_hash (RIHS01,
                         as rosbags writes it), serialization_format cdr and the topics' offered QoS
                         (reliable, volatile, keep all: :func:`linear_slam_ros.ros.bagio.qos`)
    journal_0.mcap       the records of the first session (one new storage file per Journal.open)
    journal_1.mcap       the next session's, and so on
    .metadata.yaml.tmp   transient: metadata.yaml being replaced (temporary file, fsync, rename)
    .lock                flock'ed while a Journal is open: one writer at a time (a second open raises)
    .journal_<k>.mcap.tmp  transient: an unclosed file being sealed by Journal.open (see Readers)
    journal_<k>.mcap.damaged  a copy of a file whose tail was damaged (not merely cut), kept when sealing

A storage file is MCAP (profile ``ros2``) WITHOUT chunks, so each record reaches the file as it
is appended: the magic, a Header, the Schema (``ros2msg``), a Metadata record ``rosbag2``
(``serialized_metadata``: version 9, so rosbag2 reads the QoS in the version-9 form), then per
topic a Channel (``cdr``; ``offered_qos_profiles``, ``topic_type_hash``) before its first
Message. Each Message: log time = publish time = the receive time given to :meth:`Journal.append`
(ns; made non-decreasing within a file, see there), sequence = the record's journal index
(mod 2**32; the reader unwraps it, and reports a gap or a record out of order), data = the raw CDR bytes. :meth:`Journal.close`
appends DataEnd, the summary (schema, channels, statistics, metadata index) and the Footer.

Crash safety:

- Process kill (``kill -9``) at any instant: every :meth:`~Journal.append` copies the complete
  record into a shared memory map of the storage file (:class:`_MappedFile`: the OS's file cache,
  no system call) before it returns, its first byte last, so the files hold every record appended
  so far, and at most the last one without its first byte (its copy was interrupted). The reader
  drops such a record (and a file cut short in a record, e.g. by a copy), never returns a part of
  one, and never raises for one. While a session runs, its file ends in zero bytes reserved ahead;
  :meth:`Journal.close` trims them, and :meth:`Journal.open` seals a file a crash left so.
- Power cut: the storage file is fsynced every ``fsync_period_s`` seconds (default 1.0) or every
  ``fsync_every`` records (default 200), whichever comes first (checked at each append; call
  :meth:`Journal.maybe_sync` from a timer so a journal that falls quiet still gets its last
  records synced), and on :meth:`~Journal.flush` and :meth:`~Journal.close`. A power cut thus
  loses at most the last 1 s or 200 submaps (the records appended since the last fsync). The
  node calls ``flush(fsync=True)`` before each snapshot, so a snapshot never counts records the
  disk does not hold.
- Cost, measured on the 6,898 VicPark6898 local maps (CDR 1.1 kB each on average; 2-core VM,
  other processes busy; side by side with the previous writer, which wrote each record through
  mcap's ``Writer`` and flushed it with a system call): an append takes 5.5 us of CPU and 7.3 us
  of wall time without fsync (before: 10.2 and 12.6 us), and 13.2 us of wall time (before: 24.1)
  while another thread competes for the interpreter lock at a 0.5 ms switch interval, as in the
  node. An fsync costs ~0.2-0.3 ms; the default policy does one per 200 records or 1 s, and the
  node runs it from a timer, off the joining thread.
- ``metadata.yaml`` is rewritten atomically (temporary file, fsync, rename, fsync of the folder)
  when a storage file is opened and on :meth:`~Journal.flush` and :meth:`~Journal.close`, not on
  every append: after a crash its counts and time ranges may lag the files. ``ros2 bag reindex``
  or this module's reader restore exactness: :func:`read_journal` ignores the counts and reads
  the files themselves, and :meth:`Journal.open` rewrites metadata.yaml from what it read.

Readers: :func:`read_journal` reads any state, including an unclosed or truncated file and the
file a running node is still appending to. rosbags (``rosbags.rosbag2.Reader``, so
:func:`linear_slam_ros.ros.bagio.read_messages`) reads only closed files (it needs the footer):
:meth:`Journal.open` therefore seals every unclosed file of an earlier session (rewrites its
complete records to a temporary file and renames it over the old one), so after a restart, or
once the journal is closed, the whole folder reads with rosbags and ``ros2 bag play``. rosbag2's
MCAP plugin has no message index to sort unchunked files by time and reads them in file order
(logging "attempted to read in receive timestamp order with no message index"), which is arrival
order. Not verified against a ROS install here (rosbag2 is not on PyPI).
"""

from __future__ import annotations

import bisect
import contextlib
import fcntl
import logging
import mmap
import operator
import os
import re
import shutil
import struct
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from io import BytesIO, StringIO
from pathlib import Path, PurePath
from types import TracebackType
from typing import Any, BinaryIO, Literal, NoReturn

from mcap.data_stream import ReadDataStream, RecordBuilder
from mcap.exceptions import McapError
from mcap.opcode import Opcode
from mcap.records import Channel, Header, Metadata, Schema
from mcap.writer import LIBRARY_IDENTIFIER, CompressionType, IndexType, Writer
from rosbags.rosbag2.metadata import dump_qos_v9
from ruamel.yaml import YAML
from ruamel.yaml.error import YAMLError

from linear_slam_ros.core.durable import fsync_path
from linear_slam_ros.core.errors import LinearSlamError
from linear_slam_ros.ros.bagio import qos
from msg_adapters.bags import MSGTYPE, TYPESTORE

logger = logging.getLogger(__name__)

METADATA_NAME = "metadata.yaml"
"""The rosbag2 metadata file of the journal folder."""
DEFAULT_FSYNC_PERIOD_S = 1.0
"""Longest time between fsyncs of the storage file while records are appended, s."""
DEFAULT_FSYNC_EVERY = 200
"""Most records appended between fsyncs of the storage file."""

MCAP_MAGIC = b"\x89MCAP0\r\n"
_FILE_RE = re.compile(r"^journal_(0|[1-9][0-9]*)\.mcap$")
_TMP_METADATA = f".{METADATA_NAME}.tmp"
_LOCK_NAME = ".lock"
_OWN_FILES = frozenset({_TMP_METADATA, _LOCK_NAME})  # may be all an interrupted Journal.open left
_PROFILE = "ros2"
_LIBRARY = f"linear_slam_ros journal ({LIBRARY_IDENTIFIER})"
_ROS_DISTRO = "jazzy"
_BAG_VERSION = 9
_MAX_TIME = 2**63 - 1  # rosbag2's starting time of a bag without messages
_RECORD_HEAD = struct.Struct("<BQ")  # opcode, length of the record's body
_MESSAGE_HEAD = struct.Struct("<HIQQ")  # channel id, sequence, log time, publish time
_MESSAGE_RECORD = struct.Struct("<BQHIQQ")  # a message record up to its data: opcode, length, then _MESSAGE_HEAD
_SCHEMA_ID = 1  # the one schema of a storage file (std_msgs/msg/Float64MultiArray)
_SEQUENCE_MASK = 0xFFFFFFFF
MAPPED_INITIAL_BYTES = 1 << 20
"""Space a new storage file reserves ahead of its records, bytes (see :class:`_MappedFile`)."""
MAPPED_GROWTH_MAX_BYTES = 64 << 20
"""Most space a storage file reserves at a time when it is full, bytes (it doubles up to this step)."""

_MSGDEF = TYPESTORE.generate_msgdef(MSGTYPE, ros_version=2)[0]
_TYPE_HASH = TYPESTORE.hash_rihs01(MSGTYPE)


def _offered_qos() -> list[Any]:
    """Return the topics' offered QoS in metadata version 9's form (a new list: YAML then writes no aliases)."""
    return list(dump_qos_v9([qos(latched=False)]))


class JournalError(LinearSlamError):
    """A folder is not a journal, or a journal cannot be opened or appended to (names the path)."""


@dataclass(frozen=True)
class JournalRecord:
    """One journaled message.

    Attributes:
        index: the index it was appended with: its position in the whole journal, 0-based, across
            storage files (records lost before it do not renumber it).
        topic: the topic it was received on (``local_map`` or ``pose_graph``).
        raw: its CDR bytes (a ``std_msgs/msg/Float64MultiArray``), exactly as appended.
        log_time_ns: its receive time, ns (as stored: non-decreasing within a storage file).
    """

    index: int
    topic: str
    raw: bytes
    log_time_ns: int


@dataclass(frozen=True)
class JournalFile:
    """What the reader found in one storage file.

    Attributes:
        name: file name in the journal folder (``journal_<k>.mcap``).
        first_index: journal index of its first record (that of the next file's when it has none).
        count: complete records read from it.
        start_ns: log time of its first record, ns (``None``: no records).
        end_ns: log time of its last record, ns (``None``: no records).
        closed: whether it ends with a footer (its session called :meth:`Journal.close`).
        dropped_bytes: bytes after its last intact record that were ignored (a truncated or
            damaged tail; 0 for a closed file or a clean cut between records).
    """

    name: str
    first_index: int
    count: int
    start_ns: int | None
    end_ns: int | None
    closed: bool
    dropped_bytes: int


@dataclass(frozen=True)
class JournalContents:
    """Everything :func:`read_journal` read from a journal folder.

    Attributes:
        folder: the journal folder.
        records: the complete records, in journal order (indices increasing; a gap where records
            were lost).
        files: one entry per storage file found, in order.
        problems: one line per problem found, naming the file: a record cut short or damaged, a
            storage file missing or not MCAP, records out of sequence, an unreadable metadata.yaml.
            What a crash leaves without losing a record (a file without footer, or not yet
            listed in metadata.yaml) is not a problem: see :attr:`JournalFile.closed`.
    """

    folder: Path
    records: tuple[JournalRecord, ...]
    files: tuple[JournalFile, ...]
    problems: tuple[str, ...]

    @property
    def count(self) -> int:
        """The index the next appended record gets: one past the last complete record's (records lost
        in the middle still count)."""
        return self.records[-1].index + 1 if self.records else 0

    def after(self, count: int) -> tuple[JournalRecord, ...]:
        """Return the records a snapshot including the first ``count`` records lacks (to replay): those of index ``count`` on.

        Args:
            count: journal records the snapshot includes (>= 0). More than :attr:`count` gives an
                empty tuple: compare them to detect a journal that lost records (a power cut
                before an fsync).
        """
        if count < 0:
            raise ValueError(f"record count must be >= 0, got {count}")
        return self.records[bisect.bisect_left(self.records, count, key=lambda r: r.index):]


# ---------------------------------------------------------------------------------------- reading


@dataclass
class _Scan:
    """One storage file as read (mutable while reading)."""

    name: str
    size: int = 0
    messages: list[tuple[str, int, int, int, bytes]] = field(default_factory=list)  # topic, sequence, log, publish, data
    closed: bool = False
    state: Literal["ok", "unclosed", "truncated", "damaged", "not_mcap", "unreadable"] = "ok"
    detail: str = ""  # what stopped the reading early
    stop: int = 0  # offset where reading stopped
    in_summary: bool = False  # DataEnd seen: every message of the file was complete
    cut_opcode: int | None = None  # opcode of the record reading stopped in
    reserved: int = 0  # zero bytes after the last record: space reserved ahead (see _MappedFile)

    @property
    def dropped(self) -> int:
        return 0 if self.closed else self.size - self.stop - self.reserved

    @property
    def exact(self) -> bool:
        """Whether the file is closed and ends at its closing magic (else :meth:`Journal.open` seals it)."""
        return self.closed and self.stop == self.size


def _file_name(k: int) -> str:
    return f"journal_{k}.mcap"


def _zeros(data: bytes, start: int) -> bool:
    """Whether every byte of ``data`` from ``start`` on is zero (space a storage file reserved ahead)."""
    return not data[start:].lstrip(b"\0")


def _scan_file(path: Path) -> _Scan:
    """Read a storage file's records up to its footer, or up to the first record that is not intact."""
    scan = _Scan(path.name)
    try:
        data = path.read_bytes()
    except OSError as exc:
        scan.state, scan.detail = "unreadable", str(exc)
        return scan
    n = scan.size = len(data)
    head = data[: len(MCAP_MAGIC)]
    if head[:1] == b"\0" and _zeros(data, len(MCAP_MAGIC)) and MCAP_MAGIC[1:].startswith(head[1:].rstrip(b"\0")):
        scan.state, scan.detail, scan.reserved = "unclosed", "no records (its creation was interrupted)", n
        return scan
    if head != MCAP_MAGIC:
        if len(head) < len(MCAP_MAGIC) and MCAP_MAGIC.startswith(head):
            scan.state, scan.detail = "truncated", "in its magic"
        elif not any(head):
            scan.state, scan.detail = "damaged", "zero bytes where the magic belongs"
        else:
            scan.state, scan.detail = "not_mcap", f"bad magic {head!r}"
        return scan
    pos = len(MCAP_MAGIC)
    channels: dict[int, str] = {}
    schemas: set[int] = set()

    def stop(state: Literal["truncated", "damaged", "unclosed"], detail: str) -> None:
        scan.state, scan.detail, scan.stop = state, detail, pos
        scan.cut_opcode = data[pos] if pos < n else None

    while True:
        if pos == n:
            stop("unclosed", "no footer")
            break
        if n - pos < _RECORD_HEAD.size:
            stop("truncated", "in a record's opcode and length")
            break
        op, length = _RECORD_HEAD.unpack_from(data, pos)
        end = pos + _RECORD_HEAD.size + length
        if op == 0:
            if _zeros(data, pos):
                stop("unclosed", "no footer")
                scan.reserved = n - pos
            elif _zeros(data, end if end <= n else pos + _RECORD_HEAD.size):
                stop("truncated", "in a record whose write was interrupted (its opcode not yet written)")
                scan.reserved = n - len(data.rstrip(b"\0"))
            else:
                stop("damaged", "invalid record (opcode 0x00)")
            break
        if end > n:
            stop("truncated", f"in a record (opcode 0x{op:02x}) of {length} bytes")
            break
        body = pos + _RECORD_HEAD.size
        if pos == len(MCAP_MAGIC) and op != Opcode.HEADER:
            stop("damaged", f"first record has opcode 0x{op:02x}, not a header")
            break
        if op == Opcode.MESSAGE:
            if scan.in_summary or length < _MESSAGE_HEAD.size:
                stop("damaged", f"malformed message record ({length} bytes)")
                break
            cid, sequence, log_time, publish_time = _MESSAGE_HEAD.unpack_from(data, body)
            topic = channels.get(cid)
            if topic is None:
                stop("damaged", f"message on unknown channel {cid}")
                break
            scan.messages.append((topic, sequence, log_time, publish_time, data[body + _MESSAGE_HEAD.size : end]))
        elif op in (Opcode.HEADER, Opcode.SCHEMA, Opcode.CHANNEL) and not scan.in_summary:
            try:
                stream = ReadDataStream(BytesIO(data[body:end]))
                if op == Opcode.HEADER:
                    header = Header.read(stream)
                    if pos != len(MCAP_MAGIC) or header.profile != _PROFILE:
                        stop("damaged", f"unexpected header (profile {header.profile!r})")
                        break
                elif op == Opcode.SCHEMA:
                    schemas.add(Schema.read(stream).id)
                else:
                    channel = Channel.read(stream)
                    if channel.schema_id not in schemas:
                        stop("damaged", f"channel {channel.id} on unknown schema {channel.schema_id}")
                        break
                    channels[channel.id] = channel.topic
            except (McapError, struct.error, UnicodeDecodeError) as exc:
                stop("damaged", f"malformed record (opcode 0x{op:02x}): {type(exc).__name__}")
                break
        elif op == Opcode.DATA_END:
            scan.in_summary = True
        elif op == Opcode.FOOTER:
            tail = data[end : end + len(MCAP_MAGIC)]
            if tail == MCAP_MAGIC:
                scan.closed, scan.stop = True, end + len(MCAP_MAGIC)
                break
            if len(tail) < len(MCAP_MAGIC) and MCAP_MAGIC.startswith(tail):
                stop("truncated", "in its closing magic")
            else:
                stop("damaged", "bad closing magic")
            break
        pos = end  # anything else (metadata, summary records, unknown opcodes) is skipped
    return scan


def _listed_files(path: Path) -> list[str]:
    """Return the storage files metadata.yaml lists.

    Raises:
        ValueError: metadata.yaml cannot be read or is not rosbag2 metadata.
        JournalError: it is rosbag2 metadata of some other bag (names the path).
    """
    try:
        meta = YAML(typ="safe").load(path.read_text(encoding="utf-8"))
        info = meta["rosbag2_bagfile_information"]
        storage = info["storage_identifier"]
        listed = [PurePath(str(p)).name for p in info["relative_file_paths"]]
    except (OSError, YAMLError, UnicodeDecodeError, KeyError, TypeError) as exc:
        raise ValueError(f"{type(exc).__name__}: {exc}") from None
    if storage != "mcap":
        raise JournalError(f"{path.parent}: not a journal: its {METADATA_NAME} has storage_identifier {storage!r}, not mcap")
    others = [p for p in listed if not _FILE_RE.match(p)]
    if others:
        raise JournalError(f"{path.parent}: not a journal: its {METADATA_NAME} lists {others[0]!r}, not journal_<k>.mcap files")
    return listed


def _inventory(folder: Path) -> tuple[dict[int, Path], list[str]]:
    """Return a journal folder's storage files by number and the problems of its file list.

    Raises:
        JournalError: the folder is not a journal (see :func:`read_journal`).
    """
    if not folder.exists():
        raise JournalError(f"{folder}: not a journal: no such folder")
    if not folder.is_dir():
        raise JournalError(f"{folder}: not a journal: not a folder")
    try:
        entries = sorted(folder.iterdir())
    except OSError as exc:
        raise JournalError(f"{folder}: cannot list the journal folder: {exc}") from None
    on_disk = {int(m.group(1)): p for p in entries if (m := _FILE_RE.match(p.name))}
    problems: list[str] = []
    listed: set[int] | None = None
    meta = folder / METADATA_NAME
    if meta.exists():
        try:
            listed = {int(m.group(1)) for name in _listed_files(meta) if (m := _FILE_RE.match(name))}
        except ValueError as exc:
            if not on_disk:
                raise JournalError(f"{folder}: not a journal: {METADATA_NAME} is not rosbag2 metadata ({exc})") from None
            problems.append(f"{METADATA_NAME}: unreadable ({exc}); reading the storage files")
    elif not on_disk:
        others = [p.name for p in entries if p.name not in _OWN_FILES]
        if others:
            raise JournalError(
                f"{folder}: not a journal: no {METADATA_NAME} and no journal_<k>.mcap files (holds {', '.join(others[:3])})"
            )
    numbers = sorted(set(on_disk) | (listed or set()))
    for k in range(numbers[-1] + 1 if numbers else 0):
        name = _file_name(k)
        if k not in on_disk:
            where = f"listed in {METADATA_NAME} but missing" if listed and k in listed else "missing"
            problems.append(f"{name}: {where} (storage files run from journal_0 to journal_{numbers[-1]}): its records are lost")
    return on_disk, problems


def _index(sequence: int, previous: int) -> int | None:
    """Return the journal index of a record carrying ``sequence`` (its index mod 2**32) read after record
    ``previous`` (-1: none), or ``None`` when it cannot follow it (a sequence behind, or 2**31 ahead or more)."""
    ahead = (sequence - (previous + 1)) & _SEQUENCE_MASK
    return previous + 1 + ahead if ahead < 1 << 31 else None


def _read(folder: Path) -> tuple[JournalContents, dict[int, _Scan]]:
    """Read a journal folder: its contents, and each storage file's scan by number.

    A record's index is the one it was appended with (its MCAP sequence, mod 2**32, unwrapped
    after the record before it), not its position: when a storage file lost records (a damaged
    or truncated middle, a missing file), the records after them keep their indices, so a
    snapshot's record count still says which records it includes. A record whose sequence cannot
    follow the one before (out of order) is numbered next, and reported.
    """
    on_disk, problems = _inventory(folder)
    records: list[JournalRecord] = []
    files: list[JournalFile] = []
    scans: dict[int, _Scan] = {}
    last = -1
    for k in sorted(on_disk):
        scan = scans[k] = _scan_file(on_disk[k])
        start = len(records)
        mismatch = None
        for topic, sequence, log_time, _publish, raw in scan.messages:
            index = _index(sequence, last)
            if index is None:
                index = last + 1
                mismatch = mismatch or f"{scan.name}: record {index} carries sequence {sequence}: out of order, numbered {index}"
            elif index > last + 1:
                lost = f"record {last + 1}" if index == last + 2 else f"records {last + 1} to {index - 1}"
                mismatch = mismatch or f"{scan.name}: {lost} missing before record {index}"
            records.append(JournalRecord(index, topic, raw, log_time))
            last = index
        count = len(records) - start
        problem = _describe(scan, last if count else None)
        problems.extend(p for p in (problem, mismatch) if p)
        times = [m[2] for m in scan.messages]
        first = records[start].index if count else last + 1
        files.append(
            JournalFile(
                scan.name, first, count, min(times) if times else None, max(times) if times else None, scan.closed, scan.dropped
            )
        )
    return JournalContents(folder, tuple(records), tuple(files), tuple(problems)), scans


def _describe(scan: _Scan, last: int | None) -> str | None:
    """Return the problem line of a storage file, or ``None`` when it lost nothing.

    A file whose session ended without :meth:`Journal.close` (a kill between two records, while
    closing, or while creating the file) holds every record it was given: that is what a crash
    leaves, not a problem (:attr:`JournalFile.closed` tells it apart).
    """
    name = scan.name
    if scan.state == "unreadable":
        return f"{name}: unreadable ({scan.detail}): its records are lost"
    if scan.state == "not_mcap":
        return f"{name}: not an MCAP file ({scan.detail}): its {scan.size} bytes are ignored"
    if scan.closed or scan.size == 0 or scan.state == "unclosed" or scan.in_summary or scan.cut_opcode == Opcode.DATA_END:
        return None
    what = "truncated" if scan.state == "truncated" else f"damaged ({scan.detail})"
    where = f"after record {last}" if last is not None else "before its first record"
    return f"{name}: {what} {where} ({scan.dropped} bytes dropped)"


def read_journal(folder: str | Path) -> JournalContents:
    """Read every complete record of a journal folder, in journal order, and the problems found.

    Storage files are read in order (``journal_0.mcap``, ``journal_1.mcap``, ...: those on disk,
    whether metadata.yaml lists them or not; its counts are not used). Each is read record by
    record up to its footer; a file without one (its session crashed, or is still appending)
    is read up to its last intact record: a truncated or damaged tail is dropped and reported,
    never returned in part. Nothing is written.

    Args:
        folder: the journal folder (``<state_dir>/journal``). An empty folder is an empty journal.

    Returns:
        The records and one problem line per file that lost or may have lost records, e.g.
        ``"journal_1.mcap: truncated after record 1234 (312 bytes dropped)"`` (a file merely left
        without footer by a crash has all its records: :attr:`JournalFile.closed` is ``False``).

    Raises:
        JournalError: the folder does not exist, is not a folder, or holds something else (a
            metadata.yaml of another bag, or files but neither metadata.yaml nor journal files).
    """
    contents, _ = _read(Path(folder))
    return contents


# ---------------------------------------------------------------------------------------- writing


@dataclass(frozen=True)
class _FileStats:
    """A storage file as metadata.yaml describes it."""

    name: str
    count: int
    start_ns: int | None
    end_ns: int | None
    topics: tuple[tuple[str, int], ...]  # (topic, records) in order of first appearance


def _topic_counts(topics: Sequence[str]) -> tuple[tuple[str, int], ...]:
    counts: dict[str, int] = {}
    for t in topics:
        counts[t] = counts.get(t, 0) + 1
    return tuple(counts.items())


def _dump_yaml(value: object) -> str:
    yaml = YAML(typ="safe")
    yaml.default_flow_style = False
    out = StringIO()
    yaml.dump(value, out)
    return out.getvalue()


_CHANNEL_METADATA = {"offered_qos_profiles": _dump_yaml(_offered_qos()).strip(), "topic_type_hash": _TYPE_HASH}


def _bag_metadata(files: Sequence[_FileStats]) -> dict[str, Any]:
    """Return the rosbag2 metadata (version 9) of a journal of ``files``, in the form rosbags writes."""
    topics: dict[str, int] = {}
    for f in files:
        for topic, count in f.topics:
            topics[topic] = topics.get(topic, 0) + count

    def span(start: int | None, end: int | None) -> tuple[int, int]:
        return (start, end - start) if start is not None and end is not None else (_MAX_TIME, 0)

    starts = [f.start_ns for f in files if f.start_ns is not None]
    ends = [f.end_ns for f in files if f.end_ns is not None]
    start, duration = span(min(starts) if starts else None, max(ends) if ends else None)
    return {
        "rosbag2_bagfile_information": {
            "version": _BAG_VERSION,
            "storage_identifier": "mcap",
            "relative_file_paths": [f.name for f in files],
            "duration": {"nanoseconds": duration},
            "starting_time": {"nanoseconds_since_epoch": start},
            "message_count": sum(f.count for f in files),
            "topics_with_message_count": [
                {
                    "topic_metadata": {
                        "name": topic,
                        "type": MSGTYPE,
                        "serialization_format": "cdr",
                        "offered_qos_profiles": _offered_qos(),
                        "type_description_hash": _TYPE_HASH,
                    },
                    "message_count": count,
                }
                for topic, count in topics.items()
            ],
            "compression_format": "",
            "compression_mode": "",
            "files": [
                {
                    "path": f.name,
                    "starting_time": {"nanoseconds_since_epoch": span(f.start_ns, f.end_ns)[0]},
                    "duration": {"nanoseconds": span(f.start_ns, f.end_ns)[1]},
                    "message_count": f.count,
                }
                for f in files
            ],
            "custom_data": None,
            "ros_distro": _ROS_DISTRO,
        }
    }


def _lock(folder: Path) -> BinaryIO:
    """Take the journal's writer lock (flock on ``.lock``); return the open file: closing it releases the lock.

    The lock also goes when the process ends, or when a :class:`Journal` dropped without
    :meth:`~Journal.close` is garbage-collected.

    Raises:
        JournalError: another open :class:`Journal` (this process or another) holds it.
    """
    fh = open(folder / _LOCK_NAME, "ab")  # noqa: SIM115 - held until Journal.close()
    try:
        fcntl.flock(fh.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        fh.close()
        raise JournalError(f"journal {folder} is in use: another open Journal holds {folder / _LOCK_NAME}") from None
    return fh


def _write_metadata(folder: Path, files: Sequence[_FileStats], fsync: bool) -> None:
    """Replace metadata.yaml atomically: temporary file, fsync, rename, fsync of the folder."""
    tmp = folder / _TMP_METADATA
    with open(tmp, "w", encoding="utf-8") as f:
        f.write(_dump_yaml(_bag_metadata(files)))
        f.flush()
        if fsync:
            os.fsync(f.fileno())
    os.replace(tmp, folder / METADATA_NAME)
    if fsync:
        fsync_path(folder)


class _MappedFile:
    """A file written through a shared memory map: each :meth:`write` is a memory copy into the OS's file cache.

    Why: an ``os.write`` (or a flush of Python's buffer) releases the interpreter lock for its
    system call, and the appending thread then waits to get it back from the node's other threads
    (measured inside the node: 190-340 us of wall time per record for a 10 us append). A copy into
    a ``MAP_SHARED`` mapping needs no system call: the bytes are in the OS's page cache (the same
    pages the file reads from) when it returns, so a process kill cannot lose them, and
    :meth:`fsync` makes them durable.

    Space is reserved ahead (``posix_fallocate``, doubling from :data:`MAPPED_INITIAL_BYTES`, at
    most :data:`MAPPED_GROWTH_MAX_BYTES` at a time): the blocks are allocated before a byte is
    copied, so a full disk is an ``OSError`` from :meth:`write`, never a ``SIGBUS`` at a page fault.
    Until :meth:`close` truncates the file to what was written, it ends in zero bytes.

    Commit order: each :meth:`write` copies bytes 1..8 (a record's length), then the rest, then
    byte 0 (the record's opcode) last. A write interrupted by a kill therefore leaves a zero
    opcode where its record starts: the reader (:func:`_scan_file`) stops there and never reads a
    part of it as a record.
    """

    def __init__(self, path: Path, exclusive: bool) -> None:
        flags = os.O_RDWR | os.O_CREAT | (os.O_EXCL if exclusive else os.O_TRUNC)
        self._fd = os.open(path, flags | getattr(os, "O_CLOEXEC", 0), 0o644)
        try:
            os.posix_fallocate(self._fd, 0, MAPPED_INITIAL_BYTES)
            self._map = mmap.mmap(self._fd, MAPPED_INITIAL_BYTES)
        except BaseException:
            os.close(self._fd)
            raise
        self._pos = 0

    def write(self, data: bytes) -> int:
        """Copy ``data`` at the end (opcode byte last, see the class docstring); return its length.

        Raises:
            OSError: more space could not be reserved (e.g. the disk is full).
        """
        view = memoryview(data)
        if view.nbytes:
            self.write_record(view[: _RECORD_HEAD.size], view[_RECORD_HEAD.size :])
        return view.nbytes

    def write_record(self, head: bytes | memoryview, body: bytes | memoryview) -> None:
        """Copy ``head + body`` at the end: ``head[1:]`` (the record's length, and more), ``body``, then ``head[0]``.

        Raises:
            OSError: more space could not be reserved (e.g. the disk is full).
        """
        start = self._pos
        mid = start + len(head)
        end = mid + len(body)
        if end > len(self._map):
            self._grow(end)
        self._map[start + 1 : mid] = head[1:]
        self._map[mid:end] = body
        self._map[start] = head[0]
        self._pos = end

    def tell(self) -> int:
        """Bytes written so far."""
        return self._pos

    def fsync(self) -> None:
        """Make every written byte durable (the mapping's dirty pages are the file's)."""
        os.fsync(self._fd)

    def close(self) -> None:
        """Unmap, truncate the file to the bytes written, fsync and close it."""
        try:
            self._map.close()
            os.ftruncate(self._fd, self._pos)
            os.fsync(self._fd)
        finally:
            os.close(self._fd)

    def abandon(self) -> None:
        """Unmap and close without truncating (the next :meth:`Journal.open` seals the file)."""
        with contextlib.suppress(OSError, ValueError):
            self._map.close()
        with contextlib.suppress(OSError):
            os.close(self._fd)

    def _grow(self, needed: int) -> None:
        size = len(self._map)
        while size < needed:
            size += min(size, MAPPED_GROWTH_MAX_BYTES)
        os.posix_fallocate(self._fd, 0, size)
        self._map.resize(size)


class _StorageWriter:
    """A closed storage file written at once by mcap's ``Writer`` (unchunked): what :func:`_seal` produces."""

    def __init__(self, path: Path, name: str) -> None:
        self.path = path
        self.name = name
        self._fh = open(path, "wb")  # noqa: SIM115 - closed by close()
        try:
            self._writer = Writer(self._fh, use_chunking=False, compression=CompressionType.NONE, index_types=IndexType.ALL)
            self._writer.start(profile=_PROFILE, library=_LIBRARY)
            self._schema = self._writer.register_schema(name=MSGTYPE, encoding="ros2msg", data=_MSGDEF.encode())
            self._writer.add_metadata("rosbag2", _rosbag2_metadata(name))
        except BaseException:
            self._fh.close()
            raise
        self._channels: dict[str, int] = {}
        self._topics: list[str] = []

    def write(self, topic: str, raw: bytes, log_time_ns: int, sequence: int, publish_time_ns: int) -> None:
        """Write one message record."""
        cid = self._channels.get(topic)
        if cid is None:
            cid = self._channels[topic] = self._writer.register_channel(topic, "cdr", self._schema, dict(_CHANNEL_METADATA))
        self._writer.add_message(channel_id=cid, log_time=log_time_ns, data=raw, publish_time=publish_time_ns, sequence=sequence)
        self._topics.append(topic)

    def topics(self) -> tuple[tuple[str, int], ...]:
        return _topic_counts(self._topics)

    def close(self) -> None:
        """Write the summary and footer, fsync and close (the file is closed even if writing fails)."""
        try:
            self._writer.finish()
            self._fh.flush()
            os.fsync(self._fh.fileno())
        finally:
            self._fh.close()

    def abandon(self) -> None:
        """Close the file without writing anything more (after a failed write)."""
        with contextlib.suppress(OSError):
            self._fh.close()


def _rosbag2_metadata(name: str) -> dict[str, str]:
    """The ``rosbag2`` Metadata record's content of a storage file: rosbag2's serialized metadata (version 9)."""
    info = _bag_metadata([_FileStats(name, 0, None, None, ())])["rosbag2_bagfile_information"]
    return {"serialized_metadata": _dump_yaml(info).strip()}


def _records(*records: Header | Schema | Channel | Metadata) -> bytes:
    """The bytes of MCAP records, encoded by mcap's record classes."""
    builder = RecordBuilder()
    for record in records:
        record.write(builder)
    return builder.end()


class _LiveStorage:
    """The storage file a session appends to: MCAP records copied into a mapped file (:class:`_MappedFile`).

    It holds the records a crash would leave: magic, Header, Schema, the ``rosbag2`` Metadata, then
    per topic a Channel before its first Message, and the Messages. Each Message record is encoded
    here in one ``struct`` call (the same bytes mcap's ``Writer.add_message`` writes; with the
    memory copy, an append costs about half the CPU it did: see the module docstring).
    :meth:`close` trims the reserved space and seals the file (:func:`_seal`: rewritten by mcap's
    ``Writer`` with its summary and footer), so a closed journal file is exactly what mcap writes.
    """

    def __init__(self, folder: Path, name: str) -> None:
        self.folder = folder
        self.path = folder / name
        self.name = name
        self._fh = _MappedFile(self.path, exclusive=True)
        try:
            self._fh.write(MCAP_MAGIC)
            self._fh.write(
                _records(
                    Header(profile=_PROFILE, library=_LIBRARY),
                    Schema(id=_SCHEMA_ID, name=MSGTYPE, encoding="ros2msg", data=_MSGDEF.encode()),
                    Metadata(name="rosbag2", metadata=_rosbag2_metadata(name)),
                )
            )
        except BaseException:
            self._fh.abandon()
            raise
        self._channels: dict[str, int] = {}
        self._topics: list[str] = []
        self.count = 0
        self.start_ns: int | None = None
        self.end_ns: int | None = None
        self.last_time_ns = 0

    def write(self, topic: str, raw: bytes, log_time_ns: int, sequence: int) -> None:
        """Copy one message record (publish time = log time) into the file's cache pages (no fsync)."""
        cid = self._channels.get(topic)
        if cid is None:
            cid = len(self._channels) + 1
            channel = Channel(id=cid, topic=topic, message_encoding="cdr", schema_id=_SCHEMA_ID, metadata=dict(_CHANNEL_METADATA))
            self._fh.write(_records(channel))
            self._channels[topic] = cid
        head = _MESSAGE_RECORD.pack(Opcode.MESSAGE, _MESSAGE_HEAD.size + len(raw), cid, sequence, log_time_ns, log_time_ns)
        self._fh.write_record(head, raw)
        self.count += 1
        self._topics.append(topic)
        self.start_ns = log_time_ns if self.start_ns is None else min(self.start_ns, log_time_ns)
        self.end_ns = log_time_ns if self.end_ns is None else max(self.end_ns, log_time_ns)
        self.last_time_ns = max(self.last_time_ns, log_time_ns)

    def tell(self) -> int:
        return self._fh.tell()

    def stats(self) -> _FileStats:
        return _FileStats(self.name, self.count, self.start_ns, self.end_ns, _topic_counts(self._topics))

    def fsync(self) -> None:
        self._fh.fsync()

    def close(self) -> None:
        """Trim the reserved space, then seal the file (summary and footer); the file is closed even if sealing fails."""
        self._fh.close()
        _seal(self.folder, _scan_file(self.path))

    def abandon(self) -> None:
        """Close the file without writing anything more (after a failed write)."""
        self._fh.abandon()


def _seal(folder: Path, scan: _Scan) -> _FileStats:
    """Rewrite an unclosed storage file as a closed one holding its complete records; return its stats.

    The records go to a temporary file, fsynced, renamed over the old one: a crash meanwhile
    leaves the old file as it was. A damaged (not merely truncated) file is first copied to
    ``<name>.damaged``, so the bytes after its last intact record stay available.
    """
    path = folder / scan.name
    if scan.state == "damaged" and scan.size:
        shutil.copyfile(path, folder / f"{scan.name}.damaged")
    tmp = folder / f".{scan.name}.tmp"
    writer = _StorageWriter(tmp, scan.name)
    try:
        for topic, sequence, log_time, publish_time, raw in scan.messages:
            writer.write(topic, raw, log_time, sequence, publish_time)
    except BaseException:
        writer.abandon()
        raise
    writer.close()
    os.replace(tmp, path)
    fsync_path(folder)
    times = [m[2] for m in scan.messages]
    return _FileStats(scan.name, len(times), min(times, default=None), max(times, default=None), writer.topics())


class Journal:
    """The journal a node appends to: one new storage file per session, in a rosbag2 bag folder.

    Open it with :meth:`open`. Thread-safe: the node appends from its joining thread and flushes
    before a snapshot from another; each method holds the journal's lock while it runs (a flush
    with fsync therefore delays a concurrent append by the fsync's duration).
    """

    def __init__(
        self,
        folder: Path,
        storage: _LiveStorage,
        earlier: Sequence[_FileStats],
        next_index: int,
        fsync_period_s: float | None,
        fsync_every: int | None,
        clock: Callable[[], float],
        lock: BinaryIO,
        sync_in_append: bool = True,
    ) -> None:
        """Use :meth:`open`."""
        self._folder = folder
        self._storage = storage
        self._earlier = tuple(earlier)
        self._next_index = next_index
        self._period = fsync_period_s
        self._every = fsync_every
        self._clock = clock
        self._lock = threading.Lock()
        self._unsynced = 0
        self._last_sync = clock()
        self._closed = False
        self._failed: str | None = None
        self._clamped = False
        self._lock_file = lock  # flock'ed until close(): one writer per journal
        self._sync_in_append = sync_in_append

    @classmethod
    def open(
        cls,
        folder: str | Path,
        *,
        fsync_period_s: float | None = DEFAULT_FSYNC_PERIOD_S,
        fsync_every: int | None = DEFAULT_FSYNC_EVERY,
        clock: Callable[[], float] = time.monotonic,
        sync_in_append: bool = True,
        first_index: int = 0,
    ) -> Journal:
        """Open a journal for appending: create the folder, or add a new storage file to a journal.

        An existing journal is read first (:func:`read_journal`; its problems are logged as
        warnings): :attr:`next_index` continues from its complete records, every unclosed file of
        an earlier session is sealed (its complete records kept, a truncated tail dropped), and
        metadata.yaml is rewritten with exact counts, listing the new ``journal_<k>.mcap``.

        Args:
            folder: the journal folder (``<state_dir>/journal``); created with its parents.
            fsync_period_s: fsync the storage file when this many seconds have passed since the
                last fsync, at the next append (or :meth:`maybe_sync`); ``None``: never by time.
            fsync_every: fsync the storage file after this many records since the last fsync;
                ``None``: never by count. Both ``None``: only :meth:`flush` and :meth:`close` fsync.
            clock: monotonic time source in seconds, for tests.
            sync_in_append: apply the fsync policy inside :meth:`append`; with ``False`` only
                :meth:`maybe_sync` (from a timer, off the appending thread) and :meth:`flush` fsync,
                so an append never waits for the disk (the node's choice: the bound becomes the
                policy plus the timer's period).
            first_index: the least index the next record may get: a snapshot that includes more
                records than the journal still holds (its tail lost) must not see later records
                numbered as ones it includes.

        Raises:
            JournalError: the folder holds something else than a journal, one of its storage files
                is not an MCAP file, or the folder or the new file cannot be written.
        """
        if fsync_period_s is not None and not fsync_period_s > 0:
            raise JournalError(f"journal {folder}: fsync_period_s must be > 0 or None, got {fsync_period_s}")
        if fsync_every is not None and fsync_every < 1:
            raise JournalError(f"journal {folder}: fsync_every must be >= 1 or None, got {fsync_every}")
        folder = Path(folder)
        try:
            if folder.exists():
                _inventory(folder)  # refuse a folder that is not a journal before writing to it
            else:
                folder.mkdir(parents=True)
                fsync_path(folder.parent)
            lock = _lock(folder)
        except OSError as exc:
            raise JournalError(f"journal {folder}: cannot create or lock the folder: {exc}") from None
        try:
            contents, scans = _read(folder)
            for line in contents.problems:
                logger.warning("journal %s: %s", folder, line)
            bad = [s.name for s in scans.values() if s.state in ("not_mcap", "unreadable")]
            if bad:
                raise JournalError(f"{folder / bad[0]}: not a readable MCAP storage file: move it out of the journal to continue")
            name = _file_name(max(scans, default=-1) + 1)
            try:
                earlier = []
                for (_k, scan), info in zip(sorted(scans.items()), contents.files, strict=True):
                    if scan.exact:
                        topics = _topic_counts([m[0] for m in scan.messages])
                        earlier.append(_FileStats(scan.name, info.count, info.start_ns, info.end_ns, topics))
                    else:
                        earlier.append(_seal(folder, scan))
                        logger.info("journal %s: sealed %s (%d records)", folder, scan.name, len(scan.messages))
                storage = _LiveStorage(folder, name)
            except OSError as exc:
                raise JournalError(f"journal {folder}: cannot open {name} for appending: {exc}") from None
            try:
                storage.fsync()
                fsync_path(folder)
                next_index = max(contents.count, first_index)
                journal = cls(folder, storage, earlier, next_index, fsync_period_s, fsync_every, clock, lock, sync_in_append)
                _write_metadata(folder, journal._files(), fsync=True)
            except OSError as exc:
                storage.abandon()
                raise JournalError(f"journal {folder}: cannot open {name} for appending: {exc}") from None
        except BaseException:
            lock.close()
            raise
        logger.info("journal %s: appending to %s from record %d", folder, name, next_index)
        return journal

    @property
    def folder(self) -> Path:
        """The journal folder."""
        return self._folder

    @property
    def path(self) -> Path:
        """The storage file this session appends to."""
        return self._storage.path

    @property
    def bytes_written(self) -> int:
        """Bytes of :attr:`path` written so far (the file itself is longer while open: space reserved ahead)."""
        return self._storage.tell()

    @property
    def next_index(self) -> int:
        """The journal index the next appended record gets (= records in the journal)."""
        return self._next_index

    @property
    def closed(self) -> bool:
        """Whether :meth:`close` was called."""
        return self._closed

    def append(self, topic: str, raw: bytes, log_time_ns: int) -> int:
        """Append one message and return its journal index; fsync when the policy says so.

        The record is complete in the OS's file cache when this returns (a process kill cannot
        lose it); it is on disk after the next fsync (see the module docstring for the bound).

        Args:
            topic: the topic it was received on (``local_map``, ``pose_graph``).
            raw: its CDR bytes.
            log_time_ns: its receive time, ns since the epoch (0 <= t < 2**64). A time before the
                previous record's in this session is stored as the previous one's (and logged
                once): readers of unchunked MCAP files (rosbags) need times in file order.

        Returns:
            The record's index, 0-based across the whole journal.

        Raises:
            JournalError: the journal is closed or failed, an argument is invalid, or the write
                failed (the journal then refuses further appends: restart to continue).
        """
        if not isinstance(topic, str) or not topic:
            raise JournalError(f"journal {self._folder}: topic must be a non-empty string, got {topic!r}")
        try:
            log_time_ns = operator.index(log_time_ns)
        except TypeError:
            raise JournalError(f"journal {self._folder}: log_time_ns must be an integer, got {log_time_ns!r}") from None
        if not 0 <= log_time_ns < 2**64:
            raise JournalError(f"journal {self._folder}: log_time_ns {log_time_ns} is outside 0..2**64-1")
        data = bytes(raw)
        with self._lock:
            self._check_open()
            index = self._next_index
            stamp = log_time_ns
            if stamp < self._storage.last_time_ns:
                if not self._clamped:
                    logger.warning(
                        "journal %s: record %d's time %d ns precedes the previous record's %d ns: stored as the latter "
                        "(logged once per session)",
                        self._folder,
                        index,
                        stamp,
                        self._storage.last_time_ns,
                    )
                    self._clamped = True
                stamp = self._storage.last_time_ns
            try:
                self._storage.write(topic, data, stamp, index & _SEQUENCE_MASK)
            except Exception as exc:  # the writer's state is unknown after any failure: stop appending
                self._fail(exc)
            self._next_index += 1
            self._unsynced += 1
            if self._sync_in_append and self._sync_due():
                self._sync()
            return index

    def maybe_sync(self) -> bool:
        """Fsync the storage file if the policy says so (``fsync_period_s`` passed, or ``fsync_every`` records
        await it); return whether it did.

        Call it from a timer (period about ``fsync_period_s``) so that the last records before a
        quiet spell are synced too, and so that a journal opened with ``sync_in_append=False``
        is synced at all. The fsync itself runs without the journal's lock: appends from another
        thread go on meanwhile. Does nothing on a closed journal.
        """
        return self.sync(only_if_due=True)

    def sync(self, only_if_due: bool = False) -> bool:
        """Make every record appended so far durable (fsync), without holding the journal's lock meanwhile.

        Args:
            only_if_due: fsync only if the policy says so (see :meth:`maybe_sync`).

        Returns:
            Whether it fsynced (nothing awaited it, or the journal is closed: ``False``).
        """
        with self._lock:
            if self._closed or self._failed or not self._unsynced or (only_if_due and not self._sync_due()):
                return False
            storage, covered = self._storage, self._unsynced
        storage.fsync()  # the records appended before this call: later ones wait for the next sync
        with self._lock:
            self._unsynced = max(0, self._unsynced - covered)
            self._last_sync = self._clock()
        return True

    def flush(self, fsync: bool = True) -> None:
        """Rewrite metadata.yaml with the current counts; with ``fsync``, make every appended record durable first.

        Args:
            fsync: fsync the storage file, the new metadata.yaml and the folder (after this, a power
                cut loses nothing appended before the call). Without, metadata.yaml is still
                replaced atomically with respect to a process kill, but nothing is fsynced.

        Raises:
            JournalError: the journal is closed or failed, or writing failed.
        """
        with self._lock:
            self._check_open()
            try:
                if fsync:
                    self._sync()
                _write_metadata(self._folder, self._files(), fsync)
            except OSError as exc:
                raise JournalError(f"journal {self._folder}: flush failed: {exc}") from None

    def close(self) -> None:
        """Finish the storage file (summary and footer), fsync it and rewrite metadata.yaml; idempotent.

        Raises:
            JournalError: finishing or writing failed (the journal is closed nevertheless; the next
                :meth:`open` seals the file).
        """
        with self._lock:
            if self._closed:
                return
            self._closed = True
            try:
                if self._failed:
                    return
                self._storage.close()
                _write_metadata(self._folder, self._files(), fsync=True)
            except OSError as exc:
                raise JournalError(f"journal {self._folder}: close failed: {exc}") from None
            finally:
                self._lock_file.close()
            logger.info("journal %s: closed %s (%d records)", self._folder, self._storage.name, self._storage.count)

    def __enter__(self) -> Journal:
        """Return the journal (it is already open)."""
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc_val: BaseException | None, exc_tb: TracebackType | None
    ) -> None:
        """Close the journal."""
        self.close()

    def __repr__(self) -> str:
        state = "closed" if self._closed else "failed" if self._failed else "open"
        return f"Journal({str(self._folder)!r}, file={self._storage.name!r}, next_index={self._next_index}, {state})"

    # -------------------------------------------------------------------------------- internals

    def _files(self) -> list[_FileStats]:
        return [*self._earlier, self._storage.stats()]

    def _check_open(self) -> None:
        if self._closed:
            raise JournalError(f"journal {self._folder} is closed")
        if self._failed:
            raise JournalError(f"journal {self._folder} failed ({self._failed}): restart to continue")

    def _fail(self, exc: BaseException) -> NoReturn:
        """Refuse further appends after a failed write (the file may end in a partial record)."""
        self._failed = f"{type(exc).__name__}: {exc}"
        self._storage.abandon()
        raise JournalError(f"journal {self._folder}: cannot append to {self._storage.path}: {exc}") from None

    def _period_elapsed(self) -> bool:
        return self._period is not None and self._clock() - self._last_sync >= self._period

    def _sync_due(self) -> bool:
        return (self._every is not None and self._unsynced >= self._every) or self._period_elapsed()

    def _sync(self) -> None:
        self._storage.fsync()
        self._unsynced = 0
        self._last_sync = self._clock()
