"""bag_from_dataset --synthetic: a synthetic stream's bag decodes to exactly the generated maps."""

from __future__ import annotations

import numpy as np
import pytest

from linear_slam_ros.evaluation import city
from linear_slam_ros.pose_graph.chunks import chunk_to_local_map
from linear_slam_ros.ros.bag_from_dataset import main
from linear_slam_ros.ros.bagio import read_messages
from msg_adapters.bags import bag_parts, deserialize
from msg_adapters.layout import decode_chunk, decode_map


@pytest.mark.parametrize(("name", "as_graph"), [("garage3d-40", True), ("city2d-60", True), ("features2d-10", False)])
def test_synthetic_bag_holds_the_generated_maps(tmp_path, monkeypatch, name: str, as_graph: bool) -> None:
    monkeypatch.setenv("LINEAR_SLAM_CACHE", str(tmp_path / "cache"))
    bag = tmp_path / name
    assert main(["--synthetic", name, "--seed", "2", "--out", str(bag), *(["--as-pose-graph"] if as_graph else [])]) == 0
    stream = city.generate(name, seed=2)
    assert city.is_cached(name, 2, tmp_path / "cache")  # the offline CLI can join the same maps
    records = list(read_messages(bag))
    assert [r.topic for r in records] == ["/pose_graph" if as_graph else "/local_map"] * len(stream.maps)
    for seq, (record, expected) in enumerate(zip(records, stream.maps, strict=True), start=1):
        parts = bag_parts(deserialize(record.raw))
        if as_graph:
            chunk = decode_chunk(*parts)
            got, got_seq = chunk_to_local_map(chunk.graph), chunk.seq
        else:
            message = decode_map(*parts)
            got, got_seq = message.local_map, message.seq
        assert got_seq == seq and got.frame_id == expected.frame_id and got.end_id == expected.end_id
        assert np.array_equal(got.ids, expected.ids) and np.array_equal(got.x, expected.x)
        assert np.array_equal(got.info_dense(), expected.info_dense())


def test_synthetic_or_dataset_not_both(tmp_path) -> None:
    with pytest.raises(SystemExit):
        main(["--out", str(tmp_path / "b")])
    with pytest.raises(SystemExit):
        main(["x.tar.xz", "--synthetic", "city2d-10", "--out", str(tmp_path / "b")])
    assert main(["--synthetic", "nowhere-10", "--out", str(tmp_path / "b")]) == 2
