"""Turn a benchmark dataset or a synthetic stream into a rosbag2 bag of ``local_map`` (or ``pose_graph``) messages.

``bag_from_dataset DATASET --out bags/NAME [--rate 10] [--topic local_map] [--as-pose-graph]``
(DATASET: a folder of ``localmap_<i>.txt``, a ``.tar.xz`` archive, or another bag)
``bag_from_dataset --synthetic city2d-20000 [--seed 0] --out bags/city2d-20000 --as-pose-graph``

A synthetic stream (:mod:`linear_slam_ros.evaluation.city`: ``city2d-N``, ``garage3d-N``,
``features2d-N``) is generated from its seed and also cached, so that the offline CLI can join
the same maps (``python -m linear_slam_ros join synthetic:city2d-20000 ...``).
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
from linear_slam_ros.evaluation import city
from linear_slam_ros.io.datasets import Dataset, MapKind, parse_synthetic_name, read_dataset
from linear_slam_ros.pose_graph.graph import PoseGraph
from linear_slam_ros.ros.bagio import write_messages
from msg_adapters.bags import CUSTOM_DATASET, CUSTOM_KIND, is_bag, read_bag_submaps
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


def load_source(dataset: Path | str) -> Dataset:
    """Return the dataset at ``dataset`` (folder, archive or bag), or the synthetic stream
    ``synthetic:NAME[@SEED]`` generated (and cached for the offline CLI)."""
    if str(dataset).startswith("synthetic:"):
        name, seed = parse_synthetic_name(str(dataset))
        stream = city.generate(name, seed)
        logger.info("%s: cached in %s", stream.name, city.cache(stream))
        return stream.dataset()
    if is_bag(dataset):  # the maps the node would join, named after the bag's folder
        submaps = read_bag_submaps(dataset)
        return Dataset(Path(dataset).name, MapKind(submaps.kind), submaps.maps)
    return read_dataset(dataset)


def make_bag(
    dataset: Path | str,
    out: Path,
    rate_hz: float = 10.0,
    topic: str | None = None,
    as_pose_graph: bool = False,
    maps_per_chunk: int = 1,
    overwrite: bool = True,
) -> int:
    """Write the bag of a dataset (a path, or ``synthetic:NAME[@SEED]``); return the number of messages.

    The bag's metadata records the dataset's name and map kind (``custom_data``:
    ``linear_slam_ros.dataset``, ``linear_slam_ros.kind``), which the bag readers use.
    """
    ds = load_source(dataset)
    if as_pose_graph and ds.kind.has_features:
        raise LinearSlamError(f"{ds.name} is a pose-feature dataset: only pose-only datasets become pose_graph chunks")
    name = topic or ("pose_graph" if as_pose_graph else "local_map")
    custom = {CUSTOM_DATASET: ds.name, CUSTOM_KIND: ds.kind.value}
    return write_messages(
        out, records(ds.maps, rate_hz, name, as_pose_graph, maps_per_chunk), overwrite=overwrite, custom_data=custom
    )


def main(argv: Sequence[str] | None = None) -> int:
    """Command-line entry point."""
    ap = argparse.ArgumentParser(
        prog="bag_from_dataset", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("dataset", type=Path, nargs="?", help="folder of localmap_<i>.txt, a .tar.xz archive, or a bag")
    ap.add_argument("--synthetic", metavar="NAME", default=None,
                    help="a synthetic stream instead of a dataset: city2d-N, garage3d-N or features2d-N (e.g. city2d-20000)")
    ap.add_argument("--seed", type=int, default=0, help="seed of the synthetic stream")
    ap.add_argument("--out", type=Path, required=True, help="bag folder to create (e.g. bags/vicpark200)")
    ap.add_argument("--rate", type=float, default=10.0, help="message rate in bag time, Hz")
    ap.add_argument("--topic", default=None, help="topic name (default local_map, or pose_graph)")
    ap.add_argument("--as-pose-graph", action="store_true", help="write pose-only maps as pose_graph chunks")
    ap.add_argument("--maps-per-chunk", type=int, default=1, help="local maps per pose_graph chunk")
    args = ap.parse_args(argv)
    if (args.dataset is None) == (args.synthetic is None):
        ap.error("give either a dataset or --synthetic NAME")
    if not 1e-3 <= args.rate <= 1e6:  # bag times in int64 nanoseconds: not slower than one message in 1000 s
        ap.error(f"--rate {args.rate}: must be within [0.001, 1e6] messages a second")
    if args.maps_per_chunk < 1:
        ap.error(f"--maps-per-chunk {args.maps_per_chunk}: must be >= 1")
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    source = args.dataset if args.synthetic is None else f"synthetic:{args.synthetic}@{args.seed}"
    try:
        n = make_bag(source, args.out, args.rate, args.topic, args.as_pose_graph, args.maps_per_chunk)
    except LinearSlamError as exc:
        logger.error("%s", exc)
        return 2
    logger.info("wrote %d messages to %s", n, args.out)
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
