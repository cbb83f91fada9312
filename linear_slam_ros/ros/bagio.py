"""rosbag2 (MCAP, zstd, metadata version 9) reading and writing with rosbags, no ROS install needed."""

from __future__ import annotations

import shutil
from collections.abc import Iterable, Iterator, Mapping
from pathlib import Path
from typing import NamedTuple

from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime
from rosbags.rosbag2 import CompressionFormat, CompressionMode, Reader, StoragePlugin, Writer

from linear_slam_ros.core.errors import DatasetError
from msg_adapters.bags import MSGTYPE, TYPESTORE, read_records, serialize
from msg_adapters.layout import Encoded


class BagRecord(NamedTuple):
    """One message of a bag: topic, receive time (ns), CDR bytes, and whether the topic is latched."""

    topic: str
    time_ns: int
    raw: bytes
    latched: bool


def qos(latched: bool) -> Qos:
    """Return the offered QoS of a topic as bag metadata records it.

    The rosbags form of :func:`linear_slam_ros.ros.qos.latched_qos` (reliable, transient local,
    keep last 1) when ``latched``, else of :func:`~linear_slam_ros.ros.qos.inbound_qos`
    (reliable, volatile, keep all; depth 0 as rosbag2 writes it). Kept here, without rclpy,
    so bags can be written and read with no ROS install.
    """
    zero = QosTime(sec=0, nsec=0)
    return Qos(
        history=QosHistory.KEEP_LAST if latched else QosHistory.KEEP_ALL,
        depth=1 if latched else 0,
        reliability=QosReliability.RELIABLE,
        durability=QosDurability.TRANSIENT_LOCAL if latched else QosDurability.VOLATILE,
        deadline=zero,
        lifespan=zero,
        liveliness=QosLiveliness.AUTOMATIC,
        liveliness_lease_duration=zero,
        avoid_ros_namespace_conventions=False,
    )


def check_replaceable_bag(path: Path) -> None:
    """Raise :class:`DatasetError` unless ``path`` is a bag folder: ``metadata.yaml`` and storage files only."""
    if not path.is_dir():
        raise DatasetError(f"{path} exists and is not a bag folder: not replaced")
    entries = list(path.iterdir())
    foreign = sorted(p.name for p in entries if p.is_dir() or (p.name != "metadata.yaml" and p.suffix not in (".mcap", ".db3")))
    if not (path / "metadata.yaml").is_file() or foreign:
        what = f"it holds {', '.join(foreign[:3])}" if foreign else "it has no metadata.yaml"
        raise DatasetError(f"{path} exists and is not a bag ({what}): not replaced; give another --out or remove it")


def full_topic_name(topic: str) -> str:
    """Return ``topic`` as rosbag2 records it: fully qualified (``local_map``: ``/local_map``).

    ``ros2 bag record`` stores the names the ROS graph reports, which always start with ``/``, and
    ``ros2 bag play --topics`` / ``--exclude-topics`` and QoS override files compare names as
    written; so a bag of relative names would play nothing for ``--topics /local_map``.
    """
    return topic if topic.startswith("/") else f"/{topic}"


def write_messages(
    path: Path, records: Iterable[tuple[str, int, Encoded | bytes]], latched: set[str] | None = None, overwrite: bool = False,
    custom_data: Mapping[str, str] | None = None,
) -> int:
    """Write ``(topic, time_ns, message)`` records to an MCAP rosbag2 bag; return the count.

    Messages are ``std_msgs/msg/Float64MultiArray`` (given encoded or as CDR bytes); topics are
    written fully qualified (:func:`full_topic_name`; ``latched`` names either form);
    ``custom_data`` goes to the bag's metadata (``custom_data`` of metadata.yaml). With
    ``overwrite``, a bag already at ``path`` is replaced; anything else there is never removed.

    Raises:
        DatasetError: ``path`` exists (without ``overwrite``), or is not a bag (a file, or a folder
            without ``metadata.yaml`` or with anything but the bag's own files: a mistyped ``--out``
            must not delete a user's folder).
    """
    path = Path(path)
    if path.exists():
        if not overwrite:
            raise DatasetError(f"bag {path} exists; remove it first")
        check_replaceable_bag(path)
        shutil.rmtree(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    writer = Writer(path, version=9, storage_plugin=StoragePlugin.MCAP)
    writer.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
    for key, value in (custom_data or {}).items():
        writer.set_custom_data(key, value)
    count = 0
    connections = {}
    latched_names = {full_topic_name(t) for t in latched or ()}
    with writer:
        for given, time_ns, message in records:
            topic = full_topic_name(given)
            if topic not in connections:
                connections[topic] = writer.add_connection(
                    topic, MSGTYPE, typestore=TYPESTORE, offered_qos_profiles=[qos(topic in latched_names)]
                )
            raw = message if isinstance(message, (bytes, bytearray, memoryview)) else serialize(message)
            writer.write(connections[topic], int(time_ns), bytes(raw))
            count += 1
    return count


def read_messages(path: Path, topics: Iterable[str] | None = None) -> Iterator[BagRecord]:
    """Yield the ``Float64MultiArray`` records of a bag in time order (optionally only some topics,
    named with or without their leading ``/``); messages of other types are not read
    (:func:`other_topics` names them).

    Raises:
        DatasetError: the bag cannot be read.
    """
    for record in read_records(path, topics, msgtype=MSGTYPE):
        yield BagRecord(*record)


def other_topics(path: Path) -> dict[str, str]:
    """Return ``{topic: message type}`` of a bag's topics that are not ``Float64MultiArray``.

    Raises:
        DatasetError: the bag cannot be read.
    """
    try:
        with Reader(Path(path)) as reader:
            return {c.topic: c.msgtype for c in reader.connections if c.msgtype != MSGTYPE}
    except Exception as exc:  # rosbags raises several types for unreadable bags
        raise DatasetError(f"cannot read bag {path}: {' '.join(str(exc).split())}") from None
