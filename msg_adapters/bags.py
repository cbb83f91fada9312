"""rosbags message classes (ROS 2 Jazzy typestore) <-> core types, through :mod:`msg_adapters.layout`;
and a rosbag2 bag of ``local_map`` / ``pose_graph`` messages read back as local maps."""

from __future__ import annotations

import re
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from rosbags.interfaces import QosDurability
from rosbags.rosbag2 import Reader
from rosbags.typesys import Stores, get_typestore
from ruamel.yaml import YAML

from linear_slam_ros.core.errors import DatasetError, LinearSlamError
from linear_slam_ros.core.limits import InputLimits
from linear_slam_ros.core.local_map import FEATURE, LocalMap
from linear_slam_ros.pose_graph.chunks import chunk_to_local_map
from msg_adapters.layout import Encoded, decode_chunk, decode_map, submap_of

TYPESTORE = get_typestore(Stores.ROS2_JAZZY)
MSGTYPE = "std_msgs/msg/Float64MultiArray"
_Float64MultiArray = TYPESTORE.types[MSGTYPE]
_Layout = TYPESTORE.types["std_msgs/msg/MultiArrayLayout"]
_Dim = TYPESTORE.types["std_msgs/msg/MultiArrayDimension"]

BAG_METADATA = "metadata.yaml"
"""The file that makes a folder a rosbag2 bag."""
LOCAL_MAP_TOPIC = "local_map"
POSE_GRAPH_TOPIC = "pose_graph"
CUSTOM_DATASET = "linear_slam_ros.dataset"
"""Bag metadata ``custom_data`` key: the dataset the bag was made from (``bag_from_dataset``)."""
CUSTOM_KIND = "linear_slam_ros.kind"
"""Bag metadata ``custom_data`` key: the dataset's map kind (``2DPF``, ``2DPG``, ``3DPF``, ``3DPG``)."""


def to_bag_msg(encoded: Encoded) -> object:
    """Return a rosbags ``std_msgs/msg/Float64MultiArray`` carrying ``encoded``."""
    dims = [_Dim(label=k, size=s, stride=s) for k, s in zip(encoded.labels, encoded.sizes, strict=True)]
    return _Float64MultiArray(layout=_Layout(dim=dims, data_offset=0), data=np.asarray(encoded.data, dtype=np.float64))


def bag_parts(msg: object) -> tuple[list[str], list[int], np.ndarray, int]:
    """Return ``(labels, sizes, data, data_offset)`` of a rosbags message."""
    layout = msg.layout  # type: ignore[attr-defined]
    return (
        [d.label for d in layout.dim],
        [int(d.size) for d in layout.dim],
        np.asarray(msg.data, dtype=np.float64),  # type: ignore[attr-defined]
        int(layout.data_offset),
    )


def serialize(encoded: Encoded) -> bytes:
    """Return the CDR bytes of the message (what a bag stores and rclpy can publish raw)."""
    return bytes(TYPESTORE.serialize_cdr(to_bag_msg(encoded), MSGTYPE))


def deserialize(raw: bytes) -> object:
    """Return the rosbags message of CDR bytes."""
    return TYPESTORE.deserialize_cdr(raw, MSGTYPE)


# ---------------------------------------------------------------------------- reading bags


def is_bag(path: str | Path) -> bool:
    """Return whether ``path`` is a rosbag2 bag folder (it holds ``metadata.yaml``)."""
    p = Path(path)
    return p.is_dir() and (p / BAG_METADATA).is_file()


def read_records(
    path: str | Path, topics: Iterable[str] | None = None, msgtype: str | None = None
) -> Iterator[tuple[str, int, bytes, bool]]:
    """Yield ``(topic, time_ns, cdr_bytes, latched)`` of a bag's messages in time order (optionally only ``topics``,
    each matching with or without its leading ``/``; only messages of type ``msgtype``, e.g.
    ``std_msgs/msg/Float64MultiArray``).

    ``latched``: the topic was recorded with a transient-local QoS.

    Raises:
        DatasetError: the bag cannot be read (names the bag).
    """
    wanted = {t.lstrip("/") for t in topics} if topics is not None else None
    try:
        with Reader(Path(path)) as reader:
            conns = [c for c in reader.connections
                     if (wanted is None or c.topic.lstrip("/") in wanted) and (msgtype is None or c.msgtype == msgtype)]
            for conn, time_ns, raw in reader.messages(connections=conns):
                latched = any(
                    getattr(q, "durability", None) == QosDurability.TRANSIENT_LOCAL
                    for q in getattr(conn.ext, "offered_qos_profiles", [])
                )
                yield conn.topic, int(time_ns), bytes(raw), latched
    except Exception as exc:  # rosbags raises several types for unreadable bags
        if isinstance(exc, DatasetError):
            raise
        raise DatasetError(f"cannot read bag {path}: {' '.join(str(exc).split())}") from None


def bag_custom_data(path: str | Path) -> dict[str, str]:
    """Return the ``custom_data`` of a bag's ``metadata.yaml`` (empty when it has none).

    Raises:
        DatasetError: the metadata cannot be read.
    """
    metadata = Path(path) / BAG_METADATA
    try:
        info = YAML(typ="safe").load(metadata.read_text(encoding="utf-8"))["rosbag2_bagfile_information"]
        custom = info.get("custom_data") or {}
        return {str(k): str(v) for k, v in custom.items()}
    except Exception as exc:  # OSError, YAML errors, a document of another shape
        raise DatasetError(f"cannot read bag metadata {metadata}: {' '.join(str(exc).split())}") from None


def _submap_topic(topic: str) -> str | None:
    """Return ``local_map`` / ``pose_graph`` for those topics (also namespaced: ``/robot1/local_map``), else None."""
    base = topic.rstrip("/").rpartition("/")[2]
    return base if base in (LOCAL_MAP_TOPIC, POSE_GRAPH_TOPIC) else None


def _namespace(topic: str) -> str:
    """Return a topic's namespace (``/robot1/local_map``: ``/robot1``; ``local_map``, ``/local_map``: ``/``)."""
    return topic.rstrip("/").rpartition("/")[0] or "/"


@dataclass(frozen=True)
class BagSubmaps:
    """The submaps of a bag, as local maps in sequence-number order.

    Attributes:
        maps: one local map per message (a ``pose_graph`` chunk converted as the node converts
            it, :func:`linear_slam_ros.pose_graph.chunks.chunk_to_local_map`).
        seqs: the messages' sequence numbers, increasing.
        kind: the map kind, ``2DPF``, ``2DPG``, ``3DPF`` or ``3DPG``: the bag's recorded
            ``linear_slam_ros.kind`` when it has one, else told from the maps.
        topics: the topics read, by message count.
        custom_data: the bag's metadata ``custom_data``.
        n_repeated: messages skipped because their sequence number came earlier (as the node skips them).
    """

    maps: tuple[LocalMap, ...]
    seqs: tuple[int, ...]
    kind: str
    topics: dict[str, int] = field(default_factory=dict)
    custom_data: dict[str, str] = field(default_factory=dict)
    n_repeated: int = 0


def read_bag_submaps(path: str | Path, kind: str | None = None, limits: InputLimits | None = None) -> BagSubmaps:
    """Read every ``local_map`` and ``pose_graph`` message of a bag as a local map, as the joiner node would.

    Messages are decoded and validated with ``limits`` (default limits when None), ordered by
    sequence number; a number seen before is skipped. Other topics (``global_map``...), and topics
    of another message type (an ``OccupancyGrid`` on ``/nav/local_map`` in a ``ros2 bag record -a``),
    are ignored. ``kind``, when given, must be the bag's map kind (``2DPF``...).

    Raises:
        DatasetError: the bag cannot be read, holds no submap message, holds submaps of several
            namespaces (several robots: each numbers its own submaps), a message is malformed
            or invalid (names the bag, the topic and the message's position), its recorded kind
            is not a map kind or not the maps' (its maps of two dimensions), or ``kind`` is not the bag's.
    """
    where = str(path)
    by_seq: dict[int, LocalMap] = {}
    topics: dict[str, int] = {}
    repeated = 0
    for i, (topic, _, raw, _) in enumerate(read_records(path, msgtype=MSGTYPE)):
        submap_topic = _submap_topic(topic)
        if submap_topic is None:
            continue
        if topic not in topics and len({_namespace(t) for t in [*topics, topic]}) > 1:
            raise DatasetError(
                f"bag {where}: submap topics of several namespaces ({', '.join(sorted([*topics, topic]))}): one robot's "
                "stream per bag (each robot numbers its own submaps); `join A B --robots` joins several"
            )
        topics[topic] = topics.get(topic, 0) + 1
        try:
            parts = bag_parts(deserialize(raw))
            if submap_topic == POSE_GRAPH_TOPIC:
                chunk = decode_chunk(*parts, limits=limits)
                local_map, seq = chunk_to_local_map(chunk.graph, limits), chunk.seq
            else:
                decoded = decode_map(*parts, limits=limits)
                local_map, seq = submap_of(decoded), decoded.seq
        except LinearSlamError as exc:
            raise DatasetError(f"bag {where}: message {i + 1} on {topic}: {exc}") from None
        except Exception as exc:  # a message that is not a Float64MultiArray of ours
            raise DatasetError(f"bag {where}: message {i + 1} on {topic} cannot be decoded: {exc}") from None
        if seq in by_seq:
            repeated += 1
            continue
        by_seq[seq] = local_map
    if not by_seq:
        raise DatasetError(f"bag {where}: no {LOCAL_MAP_TOPIC} or {POSE_GRAPH_TOPIC} messages")
    seqs = tuple(sorted(by_seq))
    maps = tuple(by_seq[s] for s in seqs)
    other = next((i for i, m in enumerate(maps) if m.dim != maps[0].dim), None)
    if other is not None:
        raise DatasetError(f"bag {where}: submap seq {seqs[other]} is {maps[other].dim}D, seq {seqs[0]} {maps[0].dim}D: "
                           "one bag holds one map kind")
    custom = bag_custom_data(path)
    told = kind_of(maps)
    found = custom.get(CUSTOM_KIND) or told
    if not re.fullmatch(r"[23]D(PF|PG)", found) or int(found[0]) != maps[0].dim:
        raise DatasetError(f"bag {where}: its metadata names map kind {found!r}, its maps are {maps[0].dim}D")
    if found.endswith("PG") and told.endswith("PF"):
        raise DatasetError(f"bag {where}: its metadata names map kind {found!r} (pose graph), its maps hold features")
    if kind is not None and str(kind) != found:
        raise DatasetError(f"bag {where} holds {found} maps, not {kind}")
    return BagSubmaps(maps, seqs, found, topics, custom, repeated)


def kind_of(maps: Iterable[LocalMap]) -> str:
    """Return the map kind of local maps: their dimension, and ``PF`` when any holds a feature, else ``PG``."""
    maps = list(maps)
    features = any(bool(np.any(m.kinds == FEATURE)) for m in maps)
    return f"{maps[0].dim}D{'PF' if features else 'PG'}"

