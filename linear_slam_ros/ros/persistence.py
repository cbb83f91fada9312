"""The node's state directory: a journal of inbound messages and exact snapshots, and recovery from them.

Layout of ``state_dir``::

    journal/                  rosbag2 bag (MCAP): every accepted local_map / pose_graph message, raw
    start.json                where the current map starts (after a ``~/reset`` or a loaded state file):
                              {"journal_records": n, "state_file": path or null}; absent: at record 0, empty
    snapshots/state_<n>.npz   exact joiner state including the first n journal records (two kept)
    snapshots/blobs/<sha256>.npz
                              the large maps the snapshots name, each written once (see
                              linear_slam_ros.joiner.snapshot); those no kept snapshot names are deleted

Recovery (:meth:`StateStore.recover`): the newest snapshot that reads back intact is restored
(a truncated one, one that fails its checksum or one of another format version is reported and
the next older one tried; with none, the joiner starts empty), then the journal records after it
are replayed through the joiner. The journal is the source of truth: a snapshot only saves
replay time, so no problem with a snapshot can lose a submap, and a corrupt snapshot is never
used. A truncated journal tail (a kill while a record was being written) is reported and
dropped: that message was never joined.

A ``~/reset`` or a loaded state file (``~/load_map``, ``initial_map``) starts a new map at some
journal record n: :meth:`StateStore.mark_start` records that in ``start.json`` (atomically, fsynced)
and deletes the snapshots of the old map before anything changes. Recovery then starts from
there whatever happens to the snapshot written next: the records before n, which belong to the
cleared or replaced map, are never replayed, and with no usable snapshot from n on the map starts
empty (a reset) or from the state file again (a load).
"""

from __future__ import annotations

import dataclasses
import json
import logging
import os
import re
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from linear_slam_ros.core.durable import fsync_path
from linear_slam_ros.core.errors import LinearSlamError
from linear_slam_ros.joiner.joiner import Joiner, SavedJoiner
from linear_slam_ros.joiner.snapshot import BLOB_MIN_BYTES, BlobStore, SnapshotError, blob_names, read_snapshot, write_snapshot
from linear_slam_ros.ros.journal import Journal, read_journal

logger = logging.getLogger(__name__)

SNAPSHOTS_KEPT = 2
"""Snapshots kept in ``snapshots/``: the newest, and one to fall back to."""
_SNAPSHOT_NAME = re.compile(r"^state_(\d+)\.npz$")

Offer = Callable[[str, bytes, int], None]
"""``(topic, raw CDR bytes, journal index) -> None``: decode one journaled message and offer it to the joiner."""
START_NAME = "start.json"


@dataclass(frozen=True)
class Recovery:
    """What :meth:`StateStore.recover` found and did.

    Attributes:
        snapshot: the snapshot restored, or with none of the current map usable the state file that
            map was loaded from (``start.json``); ``None``: neither (the map started empty).
        snapshot_records: journal records the restored state included (where the map starts when
            no snapshot was restored).
        replayed: journal records replayed after it.
        problems: every problem found (a corrupt snapshot, a truncated journal), one line each.
        seconds: wall time of the recovery, s.
        journal_records: journal records the recovered state includes: the least index the next
            record may get.
    """

    snapshot: Path | None
    snapshot_records: int
    replayed: int
    problems: tuple[str, ...]
    seconds: float
    journal_records: int = 0


class StateStore:
    """A node's state directory: journal appends, periodic snapshots, recovery.

    Maps of at least ``blob_min_bytes`` bytes are written as blobs, once each (see :class:`BlobStore`).

    The journal is appended to from the node's joining thread; snapshots may be written from
    two threads (the output thread's periodic ones, ``~/reset``'s), so :meth:`write_snapshot` takes a
    lock: one snapshot, with its blobs and the deletion of unused ones, at a time.
    """

    def __init__(self, folder: Path, blob_min_bytes: int = BLOB_MIN_BYTES) -> None:
        self.folder = Path(folder)
        self.journal_dir = self.folder / "journal"
        self.snapshot_dir = self.folder / "snapshots"
        self.blobs = BlobStore(self.snapshot_dir / "blobs", blob_min_bytes)
        self._journal: Journal | None = None
        self._snapshot_lock = threading.Lock()

    def has_state(self) -> bool:
        """Return whether the folder holds a journal or a snapshot (a journal file counts without its metadata.yaml,
        which the reader does without: else the state was not resumed, and came back at the next start)."""
        journal_files = self.journal_dir.is_dir() and any(self.journal_dir.glob("journal_*.mcap"))
        return (self.journal_dir / "metadata.yaml").exists() or journal_files or bool(self.snapshots())

    def snapshots(self) -> list[tuple[int, Path]]:
        """Return ``(journal records, path)`` of the snapshots, newest first."""
        if not self.snapshot_dir.is_dir():
            return []
        found = []
        for p in self.snapshot_dir.iterdir():
            m = _SNAPSHOT_NAME.match(p.name)
            if m:
                found.append((int(m.group(1)), p))
        return sorted(found, reverse=True)

    def recover(self, joiner: Joiner, offer: Offer) -> Recovery:
        """Restore the newest good snapshot into ``joiner``, then replay the journal after it through ``offer``.

        Raises:
            JournalError: the journal folder exists but is not a journal.
            ConfigError: the snapshot was joined with another mode or map type (refuse to start:
                point ``state_dir`` elsewhere or use the same mode).
        """
        t0 = time.perf_counter()
        for folder in (self.snapshot_dir, self.blobs.folder):  # files a kill left half-written: never read, only space
            if folder.is_dir():
                for tmp in folder.glob(".*.npz.tmp"):
                    tmp.unlink(missing_ok=True)
        problems: list[str] = []
        restored: Path | None = None
        start, state_file = self._start(problems)
        records_in_snapshot = start
        for count, path in self.snapshots():
            if count < start:  # of a map cleared or replaced since (mark_start deletes them; a crash may not have)
                continue
            try:
                saved = read_snapshot(path, self.blobs)
            except SnapshotError as exc:
                problems.append(f"{exc}: falling back to an older point")
                continue
            if not isinstance(saved, SavedJoiner):
                problems.append(f"state file {path} holds no joiner state: falling back to an older point")
                continue
            joiner.restore(saved)
            restored, records_in_snapshot = path, saved.journal_records
            break
        if restored is None and state_file is not None:  # the loaded state the map started from, again
            try:
                saved = read_snapshot(state_file)
                if not isinstance(saved, SavedJoiner):
                    raise SnapshotError(f"state file {state_file} holds no joiner state")
                joiner.restore(dataclasses.replace(saved, journal_records=start))
                restored = state_file
            except (SnapshotError, OSError) as exc:
                problems.append(f"{exc}: the map it started from is lost, starting empty at journal record {start}")
        replayed, last = 0, records_in_snapshot - 1
        if self.journal_dir.exists():
            contents = read_journal(self.journal_dir)
            problems.extend(contents.problems)
            if contents.count < records_in_snapshot:
                problems.append(
                    f"journal {self.journal_dir} ends at record {contents.count}, snapshot {restored} "
                    f"includes {records_in_snapshot}: the journal lost records the snapshot still holds"
                )
            for record in contents.after(records_in_snapshot):
                offer(record.topic, record.raw, record.index)
                replayed, last = replayed + 1, record.index
        for line in problems:
            logger.warning("%s", line)
        return Recovery(restored, records_in_snapshot, replayed, tuple(problems), time.perf_counter() - t0, last + 1)

    def _start(self, problems: list[str]) -> tuple[int, Path | None]:
        """Return where the current map starts (``start.json``): its first journal record, and the state file it
        was loaded from (``None``: empty); ``(0, None)`` without the file. An unreadable file is reported."""
        path = self.folder / START_NAME
        if not path.exists():
            return 0, None
        try:
            start = json.loads(path.read_text(encoding="utf-8"))
            records, state_file = start["journal_records"], start["state_file"]
            if not isinstance(records, int) or records < 0 or not (state_file is None or isinstance(state_file, str)):
                raise ValueError(f"unexpected content {start}")
        except (OSError, ValueError, KeyError, TypeError) as exc:
            problems.append(f"{path} cannot be read ({exc}): the map is recovered from the whole journal")
            return 0, None
        return records, Path(state_file) if state_file is not None else None

    def mark_start(self, journal_records: int, state_file: Path | None = None) -> None:
        """Delete every snapshot (of the old map), then record that a new map starts at journal record
        ``journal_records``: empty (a reset), or the state of ``state_file`` (a load).

        Call it before the joiner changes, and before the snapshot of the new map, with no snapshot
        written in between (the node holds its snapshot lock). Killed before ``start.json`` is
        replaced, recovery rebuilds the old map from the journal (the reset did not happen); after,
        it starts the new one, and no snapshot of the old map is left for it to take (the newest,
        taken at the same journal count, would pass for the new map's).

        Raises:
            OSError: ``start.json`` cannot be written (the old map's snapshots are gone: recovery
                would replay its journal).
        """
        with self._snapshot_lock:
            for _, old in self.snapshots():
                old.unlink(missing_ok=True)
            if self.snapshot_dir.is_dir():
                fsync_path(self.snapshot_dir)
        self.folder.mkdir(parents=True, exist_ok=True)
        path = self.folder / START_NAME
        tmp = path.with_name(f".{START_NAME}.tmp")
        record = {"journal_records": int(journal_records), "state_file": str(state_file.resolve()) if state_file else None}
        with open(tmp, "w", encoding="utf-8") as fh:
            json.dump(record, fh)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
        fsync_path(self.folder)

    def open_journal(self, first_index: int = 0) -> Journal:
        """Open the journal for appending (a new storage file of the same bag); its next record's index is at
        least ``first_index`` (the journal records the restored state includes: :attr:`Recovery.journal_records`)."""
        if self._journal is None:  # fsyncs run on the node's sync thread (maybe_sync), never inside an append
            self._journal = Journal.open(self.journal_dir, sync_in_append=False, first_index=first_index)
        return self._journal

    @property
    def journal(self) -> Journal:
        """The open journal.

        Raises:
            LinearSlamError: :meth:`open_journal` was not called.
        """
        if self._journal is None:
            raise LinearSlamError(f"journal of {self.folder} is not open")
        return self._journal

    def write_snapshot(self, saved: SavedJoiner) -> Path:
        """Write a snapshot (atomically; only its maps not written before), then delete all but the
        :data:`SNAPSHOTS_KEPT` newest and the blobs none of those names.

        Raises:
            SnapshotError: the snapshot cannot be written (names the file).
        """
        path = self.snapshot_dir / f"state_{saved.journal_records}.npz"
        with self._snapshot_lock:
            keep = set(write_snapshot(path, saved, self.blobs))
            snapshots = self.snapshots()
            for _, old in snapshots[SNAPSHOTS_KEPT:]:
                old.unlink(missing_ok=True)
            try:
                for _, kept in snapshots[:SNAPSHOTS_KEPT]:
                    if kept != path:
                        keep |= blob_names(kept)
                self.blobs.collect(keep)
            except (SnapshotError, OSError) as exc:  # nothing is deleted unless every kept snapshot's blobs are known
                logger.warning("unused blobs of %s left in place this time: %s", self.blobs.folder, exc)
        return path

    def close(self) -> None:
        """Flush and close the journal (fsync)."""
        if self._journal is not None:
            self._journal.close()
            self._journal = None
