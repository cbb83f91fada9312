"""Turn a benchmark dataset into a rosbag2 bag of ``local_map`` (or ``pose_graph``) messages.

``bag_from_dataset DATASET --out bags/NAME [--rate 10] [--topic local_map] [--as-pose-graph]``
"""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path
from typing import Iterator, Sequence

import numpy as np

from linear_slam_ros.datasets import read_dataset
from linear_slam_ros.errors import LinearSlamError
from linear_slam_ros.geometry import pose_size
from linear_slam_ros.local_map import LocalMap
from linear_slam_ros.pose_graph import PoseGraphChunk
from linear_slam_ros.ros.bagio import write_messages
from msg_adapters.layout import Stamp, encode_chunk, encode_map

logger = logging.getLogger(__name__)

START_NS = 1_700_000_000 * 10**9
"""Bag time of the first message (a fixed, recognisable instant)."""


def star_chunk_of(local_map: LocalMap, seq: int) -> PoseGraphChunk:
    """Return the star pose-graph chunk equivalent to a pose-only local map with block-diagonal
    information (edges from its frame pose); cross-edge information terms are dropped."""
    p = pose_size(local_map.dim)
    k = local_map.n_vars
    info = local_map.info_dense()
    blocks = np.stack([info[i * p : (i + 1) * p, i * p : (i + 1) * p] for i in range(k)])
    return PoseGraphChunk(
        local_map.dim, seq, np.full(k, local_map.frame_id, dtype=np.int64), local_map.ids.copy(),
        local_map.x.reshape(k, p).copy(), blocks,
    )


def records(maps: Sequence[LocalMap], rate_hz: float, topic: str, as_pose_graph: bool) -> Iterator[tuple[str, int, object]]:
    """Yield ``(topic, time_ns, encoded)`` for each local map, ``seq`` 1..N, at ``rate_hz``."""
    period = int(round(1e9 / rate_hz))
    for i, m in enumerate(maps, start=1):
        t = START_NS + (i - 1) * period
        stamp = Stamp(t // 10**9, t % 10**9)
        if as_pose_graph:
            yield topic, t, encode_chunk(star_chunk_of(m, i), stamp)
        else:
            yield topic, t, encode_map(m, i, stamp)


def make_bag(dataset: Path, out: Path, rate_hz: float = 10.0, topic: str | None = None, as_pose_graph: bool = False, overwrite: bool = True) -> int:
    """Write the bag of a dataset; return the number of messages."""
    ds = read_dataset(dataset)
    if as_pose_graph and ds.kind.has_features:
        raise LinearSlamError(f"{ds.name} is a pose-feature dataset: only pose-only datasets become pose_graph chunks")
    name = topic or ("pose_graph" if as_pose_graph else "local_map")
    return write_messages(out, records(ds.maps, rate_hz, name, as_pose_graph), overwrite=overwrite)


def main(argv: Sequence[str] | None = None) -> int:
    """Command-line entry point."""
    ap = argparse.ArgumentParser(prog="bag_from_dataset", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("dataset", type=Path, help="folder of localmap_<i>.txt or a .tar.xz archive")
    ap.add_argument("--out", type=Path, required=True, help="bag folder to create (e.g. bags/vicpark200)")
    ap.add_argument("--rate", type=float, default=10.0, help="message rate in bag time, Hz")
    ap.add_argument("--topic", default=None, help="topic name (default local_map, or pose_graph)")
    ap.add_argument("--as-pose-graph", action="store_true", help="write pose-only maps as pose_graph chunks")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    try:
        n = make_bag(args.dataset, args.out, args.rate, args.topic, args.as_pose_graph)
    except LinearSlamError as exc:
        logger.error("%s", exc)
        return 2
    logger.info("wrote %d messages to %s", n, args.out)
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
