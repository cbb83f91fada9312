"""Message contract: bit-exact round trips through rclpy and rosbags classes; every error branch."""

from __future__ import annotations

import numpy as np
import pytest

from linear_slam_ros.core.errors import GraphError, InvalidMapError, MessageError
from linear_slam_ros.evaluation.synthetic import make_world, noisy_local_maps
from linear_slam_ros.joining.divide_conquer import join_divide_and_conquer
from linear_slam_ros.pose_graph.graph import PoseGraph
from msg_adapters import MAP_KIND_GLOBAL, Stamp, decode_chunk, decode_map, encode_chunk, encode_map
from msg_adapters.bags import bag_parts, deserialize, serialize, to_bag_msg
from msg_adapters.ros import parts, to_msg


def _maps(dim, rng):
    world = make_world(dim, 16, 20, rng)
    maps = noisy_local_maps(world, rng, steps_per_map=4)
    return maps[1], join_divide_and_conquer(maps)


def _assert_same(a, b):
    np.testing.assert_array_equal(a.ids, b.ids)
    np.testing.assert_array_equal(a.kinds, b.kinds)
    assert a.x.tobytes() == b.x.tobytes()
    assert a.info_dense().tobytes() == b.info_dense().tobytes()
    assert (a.dim, a.frame_id, a.end_id) == (b.dim, b.frame_id, b.end_id)


def _chunk(dim=2):
    p = 3 if dim == 2 else 6
    info = np.stack([np.eye(p) * (k + 1) for k in range(3)])
    measurements = np.arange(3 * p, dtype=float).reshape(3, p) / 7
    return PoseGraph.from_edges(np.array([3, 3, 3]), np.array([4, 9, 4]), measurements, info, dim=dim)


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("transport", ["rclpy", "rosbags", "cdr"])
def test_map_round_trip_is_bit_exact(dim, transport, rng):
    local, global_map = _maps(dim, rng)
    for m, kind, stats in ((local, 0, None), (global_map, MAP_KIND_GLOBAL, {"n_joined": 4.0, "join_ms_p99": 1.5})):
        enc = encode_map(m, 17, Stamp(1_700_000_000, 123_456_789), kind, 4, stats)
        if transport == "rclpy":
            back = decode_map(*parts(to_msg(enc)))
        elif transport == "rosbags":
            back = decode_map(*bag_parts(to_bag_msg(enc)))
        else:
            back = decode_map(*bag_parts(deserialize(serialize(enc))))
        _assert_same(back.local_map, m)
        assert (back.seq, back.stamp, back.map_kind, back.n_submaps) == (17, Stamp(1_700_000_000, 123_456_789), kind, 4)
        if stats:
            assert back.stats["n_joined"] == 4.0 and back.stats["join_ms_p99"] == 1.5 and back.stats["n_rejected"] == 0.0


def test_rclpy_message_carries_labels_and_cdr_crosses_libraries(rng):
    local, _ = _maps(2, rng)
    enc = encode_map(local, 3)
    msg = to_msg(enc)
    assert [d.label for d in msg.layout.dim] == ["header", "var_ids", "var_kinds", "state", "info_rows", "info_cols", "info_vals"]
    assert all(d.size == d.stride for d in msg.layout.dim)
    from rclpy.serialization import deserialize_message, serialize_message
    from std_msgs.msg import Float64MultiArray

    # CDR written by rosbags reads back in rclpy, and the reverse (padding bytes may differ)
    from_bag = deserialize_message(serialize(enc), Float64MultiArray)
    assert from_bag == msg
    _assert_same(decode_map(*bag_parts(deserialize(serialize_message(msg)))).local_map, local)


@pytest.mark.parametrize("dim", [2, 3])
def test_chunk_round_trip_is_bit_exact(dim):
    chunk = _chunk(dim)
    rclpy_back = decode_chunk(*parts(to_msg(encode_chunk(chunk, 4, Stamp(5, 6)))))
    bag_back = decode_chunk(*bag_parts(deserialize(serialize(encode_chunk(chunk, 4)))))
    for back, stamp in ((rclpy_back, Stamp(5, 6)), (bag_back, Stamp())):
        for name in ("from_ids", "to_ids", "measurements", "information", "pose_ids"):
            assert getattr(back.graph, name).tobytes() == getattr(chunk, name).tobytes()
        assert back.seq == 4 and back.graph.dim == dim and back.stamp == stamp
        assert back.graph.name == "pose-graph chunk 4"


def _enc(rng):
    local, _ = _maps(2, rng)
    return encode_map(local, 9)


def _mutate(enc, segment, values):
    labels, sizes = list(enc.labels), list(enc.sizes)
    data = []
    pos = 0
    for lab, size in zip(labels, sizes, strict=True):
        data.append(np.asarray(values, dtype=float) if lab == segment else enc.data[pos : pos + size])
        pos += size
    return labels, [len(d) for d in data], np.concatenate(data)


def test_map_message_errors(rng):
    enc = _enc(rng)
    labels, sizes, data = list(enc.labels), list(enc.sizes), enc.data
    header = data[: sizes[0]].copy()
    state_start = sizes[0] + sizes[1] + sizes[2]
    cases = [
        ((labels, sizes, data, 3), "layout.data_offset must be 0, got 3"),
        ((labels[:-1], sizes, data), "6 labels for 7 sizes"),
        ((labels, sizes, data[:-1]), "layout sizes add up to .* but data has"),
        ((labels[:3] + ["header"] + labels[4:], sizes, data), "segment 'header' appears twice"),
        ((labels[:-1] + ["other"], sizes, data), "missing segment\\(s\\) \\['info_vals'\\]"),
        (_mutate(enc, "state", np.r_[np.nan, data[state_start + 1 : state_start + sizes[3]]]),
         "non-finite values in segment\\(s\\) \\['state'\\]"),
        (_mutate(enc, "header", header[:5]), "header has 5 values, format 1 needs 9"),
        (_mutate(enc, "header", np.r_[2, header[1:]]), "unsupported format version 2"),
        (_mutate(enc, "header", np.r_[header[0], 4, header[2:]]), "dimension must be 2 or 3, got 4"),
        (_mutate(enc, "header", np.r_[header[:4], -1, header[5:]]), "invalid stamp -1 s"),
        (_mutate(enc, "header", np.r_[header[:2], 2, header[3:]]), "map_kind must be 0 \\(local\\) or 1 \\(global\\), got 2"),
        (_mutate(enc, "header", np.r_[header[:3], 0.5, header[4:]]), "segment 'header' must hold integers"),
        (_mutate(enc, "var_kinds", np.zeros(3)), "var_ids but 3 var_kinds"),
        (_mutate(enc, "info_rows", [0.0]), "info_rows, info_cols, info_vals sizes differ"),
    ]
    for args, match in cases:
        with pytest.raises(MessageError, match=match):
            decode_map(*args)


def test_map_message_information_errors():
    from linear_slam_ros.core.local_map import LocalMap

    m = LocalMap(2, 0, None, np.array([1]), np.array([1], np.int8), np.zeros(2), np.eye(2))
    enc = encode_map(m, 1)
    for rows, cols, vals, match in (
        ([0, 5], [0, 1], [1.0, 1.0], "information index out of range for a state of 2 values"),
        ([1, 0], [0, 1], [1.0, 1.0], "must be in the upper triangle"),
        ([0, 0], [0, 0], [1.0, 1.0], "repeated information entry"),
    ):
        labels, sizes, data = _mutate(enc, "info_rows", rows)
        enc2 = type(enc)(tuple(labels), tuple(sizes), data)
        labels, sizes, data = _mutate(enc2, "info_cols", cols)
        enc3 = type(enc)(tuple(labels), tuple(sizes), data)
        with pytest.raises(MessageError, match=match):
            decode_map(*_mutate(enc3, "info_vals", vals))
    # a well-formed message of an invalid map: the map's own error
    with pytest.raises(InvalidMapError, match="'local map seq 1': information matrix is not positive definite"):
        decode_map(*_mutate(enc, "info_vals", [-1.0, 1.0]))
    with pytest.raises(InvalidMapError, match="variable kind must be 0 \\(pose\\) or 1 \\(feature\\), got 3"):
        decode_map(*_mutate(enc, "var_kinds", [3.0]))


def test_chunk_message_errors():
    enc = encode_chunk(_chunk(), 4)
    header = enc.data[: enc.sizes[0]]
    with pytest.raises(MessageError, match="map_kind must be 2 for a pose-graph chunk, got 0"):
        decode_chunk(*_mutate(enc, "header", np.r_[header[:2], 0, header[3:]]))
    with pytest.raises(MessageError, match="segment 'edge_to' has 2 values, 3 edges need 3"):
        decode_chunk(*_mutate(enc, "edge_to", [1.0, 2.0]))
    with pytest.raises(GraphError, match="edge 0 connects pose 3 to itself"):
        decode_chunk(*_mutate(enc, "edge_to", [3.0, 4.0, 5.0]))
    with pytest.raises(GraphError, match="^pose-graph chunk 4: information of edge 1 \\(3->9\\) is not positive definite$"):
        decode_chunk(*_mutate(enc, "information", np.r_[enc.data[-27:-18], -enc.data[-18:-9], enc.data[-9:]]))


def _feature_map(dim, rng):
    from linear_slam_ros.feature_only.conversion import to_feature_only
    from linear_slam_ros.feature_only.joining import join_features_sequential
    from linear_slam_ros.feature_only.precondition import precondition

    world = make_world(dim, 12, 20, rng)
    groups = precondition(noisy_local_maps(world, rng, steps_per_map=4, sensor_range=9))
    return join_features_sequential([to_feature_only(g) for g in groups])


@pytest.mark.parametrize("dim", [2, 3])
def test_feature_only_map_round_trip_is_bit_exact(dim, rng):
    from msg_adapters import decode_feature_map, encode_feature_map

    fmap = _feature_map(dim, rng)
    enc = encode_feature_map(fmap, 9, Stamp(3, 4), MAP_KIND_GLOBAL, 5, {"n_joined": 5.0})
    assert "frame_features" in enc.labels
    for back in (decode_feature_map(*parts(to_msg(enc))), decode_feature_map(*bag_parts(deserialize(serialize(enc))))):
        m = back.feature_map
        assert m.frame_ids == fmap.frame_ids and m.dim == dim
        np.testing.assert_array_equal(m.ids, fmap.ids)
        assert m.x.tobytes() == fmap.x.tobytes()
        np.testing.assert_array_equal(np.asarray(m.info), np.asarray(fmap.info))
        assert (back.seq, back.stamp, back.n_submaps, back.stats["n_joined"]) == (9, Stamp(3, 4), 5, 5.0)


def test_feature_only_and_pose_frame_messages_are_not_confused(rng):
    from msg_adapters import decode_feature_map, encode_feature_map

    fmap = _feature_map(2, rng)
    enc = encode_feature_map(fmap, 2)
    match = "a feature-only map \\(segment 'frame_features'\\); decode it with decode_feature_map"
    with pytest.raises(MessageError, match=match):
        decode_map(enc.labels, enc.sizes, enc.data)
    plain = encode_map(_maps(2, rng)[0], 3)
    with pytest.raises(MessageError, match="no 'frame_features' segment: not a feature-only map"):
        decode_feature_map(plain.labels, plain.sizes, plain.data)
    k = enc.labels.index("var_kinds")
    start = sum(enc.sizes[:k])
    data = enc.data.copy()
    data[start] = 0.0  # a pose among the variables
    with pytest.raises(InvalidMapError, match="every variable must be a feature"):
        decode_feature_map(enc.labels, enc.sizes, data)
    f = enc.labels.index("frame_features")
    data = enc.data.copy()
    data[sum(enc.sizes[:f]) + 1] = data[sum(enc.sizes[:f])]  # F_X == F_O
    with pytest.raises(InvalidMapError, match="a 2D frame needs 2 distinct features"):
        decode_feature_map(enc.labels, enc.sizes, data)
