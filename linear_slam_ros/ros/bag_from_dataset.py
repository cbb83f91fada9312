"""Turn a benchmark dataset into a rosbag2 bag of ``local_map`` (or ``pose_graph``) messages.

``bag_from_dataset DATASET --out bags/NAME [--rate 10] [--topic local_map] [--as-pose-graph]``
"""

from __future__ import annotations

import argparse
import logging
import sys
from collections.abc import Iterator, Sequence
from pathlib import Path

import numpy as np

from linear_slam_ros.core.errors import LinearSlamError
from linear_slam_ros.core.geometry import pose_size
from linear_slam_ros.core.local_map import LocalMap
from linear_slam_ros.io.datasets import read_dataset
from linear_slam_ros.pose_graph.graph import PoseGraph
from linear_slam_ros.ros.bagio import write_messages
from msg_adapters.layout import Encoded, Stamp, encode_chunk, encode_map

logger = logging.getLogger(__name__)

START_NS = 1_700_000_000 * 10**9
"""Bag time of the first message (a fixed, recognisable instant)."""


def chunk_of(maps: Sequence[LocalMap], seq: int) -> PoseGraph:
    """Return pose-graph chunk ``seq`` of consecutive pose-only local maps: each map's edges from
    its frame pose to its poses (information: the map's diagonal blocks; cross terms dropped)."""
    p = pose_size(maps[0].dim)
    f, t, z, info = [], [], [], []
    for m in maps:
        dense = m.info_dense()
        for i in range(m.n_vars):
            f.append(m.frame_id)
            t.append(int(m.ids[i]))
            z.append(m.x[i * p : (i + 1) * p])
            info.append(dense[i * p : (i + 1) * p, i * p : (i + 1) * p])
    return PoseGraph.from_edges(
        np.array(f, np.int64), np.array(t, np.int64), np.array(z), np.array(info), dim=maps[0].dim, name=f"pose-graph chunk {seq}"
    )


def records(
    maps: Sequence[LocalMap], rate_hz: float, topic: str, as_pose_graph: bool, maps_per_chunk: int = 1
) -> Iterator[tuple[str, int, Encoded]]:
    """Yield ``(topic, time_ns, encoded)`` messages, ``seq`` 1..N, at ``rate_hz``.

    Local maps go one per message; as pose-graph chunks, ``maps_per_chunk`` consecutive maps'
    edges make one chunk (more than one makes chains with loop closures, estimated by LAGO).
    """
    period = int(round(1e9 / rate_hz))
    groups = [maps[i : i + maps_per_chunk] for i in range(0, len(maps), maps_per_chunk)] if as_pose_graph else [[m] for m in maps]
    for i, group in enumerate(groups, start=1):
        t = START_NS + (i - 1) * period
        stamp = Stamp(t // 10**9, t % 10**9)
        if as_pose_graph:
            yield topic, t, encode_chunk(chunk_of(group, i), i, stamp)
        else:
            yield topic, t, encode_map(group[0], i, stamp)


def make_bag(
    dataset: Path,
    out: Path,
    rate_hz: float = 10.0,
    topic: str | None = None,
    as_pose_graph: bool = False,
    maps_per_chunk: int = 1,
    overwrite: bool = True,
) -> int:
    """Write the bag of a dataset; return the number of messages."""
    ds = read_dataset(dataset)
    if as_pose_graph and ds.kind.has_features:
        raise LinearSlamError(f"{ds.name} is a pose-feature dataset: only pose-only datasets become pose_graph chunks")
    name = topic or ("pose_graph" if as_pose_graph else "local_map")
    return write_messages(out, records(ds.maps, rate_hz, name, as_pose_graph, maps_per_chunk), overwrite=overwrite)


def main(argv: Sequence[str] | None = None) -> int:
    """Command-line entry point."""
    ap = argparse.ArgumentParser(
        prog="bag_from_dataset", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("dataset", type=Path, help="folder of localmap_<i>.txt or a .tar.xz archive")
    ap.add_argument("--out", type=Path, required=True, help="bag folder to create (e.g. bags/vicpark200)")
    ap.add_argument("--rate", type=float, default=10.0, help="message rate in bag time, Hz")
    ap.add_argument("--topic", default=None, help="topic name (default local_map, or pose_graph)")
    ap.add_argument("--as-pose-graph", action="store_true", help="write pose-only maps as pose_graph chunks")
    ap.add_argument("--maps-per-chunk", type=int, default=1, help="local maps per pose_graph chunk")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    try:
        n = make_bag(args.dataset, args.out, args.rate, args.topic, args.as_pose_graph, args.maps_per_chunk)
    except LinearSlamError as exc:
        logger.error("%s", exc)
        return 2
    logger.info("wrote %d messages to %s", n, args.out)
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
