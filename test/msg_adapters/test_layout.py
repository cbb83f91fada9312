"""Message contract: bit-exact round trips through rclpy and rosbags classes; every error branch."""

from __future__ import annotations

import inspect
import json
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
import scipy.sparse as sp

from linear_slam_ros.core.errors import GraphError, InvalidMapError, MessageError
from linear_slam_ros.core.limits import NODE_LIMITS, InputLimits
from linear_slam_ros.core.local_map import LocalMap
from linear_slam_ros.evaluation.synthetic import make_world, noisy_local_maps
from linear_slam_ros.joining.divide_conquer import join_divide_and_conquer
from linear_slam_ros.pose_graph.chunks import chunk_to_local_map
from linear_slam_ros.pose_graph.graph import PoseGraph
from msg_adapters import (
    MAP_KIND_GLOBAL,
    Stamp,
    decode_chunk,
    decode_map,
    decode_map_summary,
    encode_chunk,
    encode_map,
    submap_of,
)
from msg_adapters.bags import bag_parts, deserialize, serialize, to_bag_msg
from msg_adapters.cdr import to_cdr
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
@pytest.mark.parametrize("transport", ["rclpy", "rosbags", "cdr", "to_cdr"])
def test_map_round_trip_is_bit_exact(dim, transport, rng):
    local, global_map = _maps(dim, rng)
    for m, kind, stats in ((local, 0, None), (global_map, MAP_KIND_GLOBAL, {"n_joined": 4.0, "join_ms_p99": 1.5})):
        enc = encode_map(m, 17, Stamp(1_700_000_000, 123_456_789), kind, 4, stats)
        if transport == "rclpy":
            back = decode_map(*parts(to_msg(enc)))
        elif transport == "rosbags":
            back = decode_map(*bag_parts(to_bag_msg(enc)))
        elif transport == "cdr":
            back = decode_map(*bag_parts(deserialize(serialize(enc))))
        else:  # the node's own writer, read by rosbags
            back = decode_map(*bag_parts(deserialize(to_cdr(enc).tobytes())))
        _assert_same(back.local_map, m)
        assert (back.seq, back.stamp, back.map_kind, back.n_submaps) == (17, Stamp(1_700_000_000, 123_456_789), kind, 4)
        if stats:
            assert back.stats["n_joined"] == 4.0 and back.stats["join_ms_p99"] == 1.5 and back.stats["n_rejected"] == 0.0


def test_only_a_local_map_is_a_submap(rng):
    """A global map echoed onto local_map would count every measurement in it twice."""
    local, global_map = _maps(2, rng)
    assert submap_of(decode_map(*bag_parts(to_bag_msg(encode_map(local, 3))))) is not None
    echoed = decode_map(*bag_parts(to_bag_msg(encode_map(global_map, 3, map_kind=MAP_KIND_GLOBAL))))
    with pytest.raises(MessageError, match=r"global map seq 3: map_kind 1 is a global map \(a joiner's output\); "
                                           r"only local maps \(map_kind 0\) are joined"):
        submap_of(echoed)


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


@pytest.mark.parametrize("chunk_bytes", [8, 40, 1 << 20])
def test_message_data_is_copied_in_chunks_bit_exactly(chunk_bytes, rng, monkeypatch):
    import msg_adapters.ros

    monkeypatch.setattr(msg_adapters.ros, "COPY_CHUNK_BYTES", chunk_bytes)  # 40: a partial last chunk
    local, _ = _maps(2, rng)
    enc = encode_map(local, 3)
    assert enc.data.nbytes % 40 != 0 and enc.data.nbytes > 40
    msg = to_msg(enc)
    assert msg.data.typecode == "d" and msg.data.tobytes() == enc.data.tobytes()
    _assert_same(decode_map(*parts(msg)).local_map, local)


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


@pytest.mark.parametrize("dim", [2, 3])
def test_map_summary_is_the_header_and_stats_of_the_decoded_map(dim, rng):
    local, global_map = _maps(dim, rng)
    for m, kind, stats in ((local, 0, None), (global_map, MAP_KIND_GLOBAL, {"n_joined": 4.0, "join_ms_p99": 1.5})):
        enc = encode_map(m, 17, Stamp(1_700_000_000, 123_456_789), kind, 4, stats)
        raw_parts = bag_parts(deserialize(serialize(enc)))
        full, summary = decode_map(*raw_parts), decode_map_summary(*raw_parts)
        assert (summary.dim, summary.map_kind, summary.seq, summary.stamp, summary.n_submaps, summary.stats) == (
            dim, full.map_kind, full.seq, full.stamp, full.n_submaps, full.stats)


def test_map_summary_reads_no_map_and_checks_the_header(rng):
    enc = _enc(rng)
    labels, sizes, data = list(enc.labels), list(enc.sizes), enc.data
    header = data[: sizes[0]].copy()
    state_start = sizes[0] + sizes[1] + sizes[2]
    bad_state = _mutate(enc, "state", np.r_[np.nan, data[state_start + 1 : state_start + sizes[3]]])
    with pytest.raises(MessageError, match="non-finite values in segment"):
        decode_map(*bad_state)
    assert decode_map_summary(*bad_state).n_submaps == decode_map_summary(labels, sizes, data).n_submaps
    cases = [
        ((labels, sizes, data, 3), "layout.data_offset must be 0, got 3"),
        ((labels, sizes, data[:-1]), "layout sizes add up to .* but data has"),
        ((["other"] + labels[1:], sizes, data), "missing segment\\(s\\) \\['header'\\]"),
        (_mutate(enc, "header", header[:5]), "header has 5 values, format 1 needs 9"),
        (_mutate(enc, "header", np.r_[2, header[1:]]), "unsupported format version 2"),
        (_mutate(enc, "header", np.r_[header[:3], np.inf, header[4:]]), "non-finite values in segment\\(s\\) \\['header'\\]"),
    ]
    for args, match in cases:
        with pytest.raises(MessageError, match=match):
            decode_map_summary(*args)


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
        # builtin_interfaces/Time.sec is int32: 2**31 s would wrap in the node's output stamps
        (_mutate(enc, "header", np.r_[header[:4], 2**31, header[5:]]),
         "invalid stamp 2147483648 s 0 ns \\(seconds in \\[0, 2147483647\\]"),
        (_mutate(enc, "header", np.r_[header[:5], 1e9, header[6:]]), "invalid stamp .* s 1000000000 ns"),
        (_mutate(enc, "header", np.r_[header[:2], 2, header[3:]]), "map_kind must be 0 \\(local\\) or 1 \\(global\\), got 2"),
        (_mutate(enc, "header", np.r_[header[:3], 0.5, header[4:]]), "segment 'header' must hold integers"),
        (_mutate(enc, "header", np.r_[header[:6], -3, header[7:]]),
         "header frame_pose_id -3, end_pose_id .*: pose ids are >= 0 \\(-1: none\\)"),
        (_mutate(enc, "header", np.r_[header[:7], -2, header[8:]]), "end_pose_id -2"),
        (_mutate(enc, "header", np.r_[header[:8], -1]), "n_submaps -1"),
        (_mutate(enc, "header", np.r_[header[:6], -1, header[7:]]), "frame_pose_id -1: a map in a pose's frame needs"),
        (_mutate(enc, "var_kinds", np.zeros(3)), "var_ids but 3 var_kinds"),
        (_mutate(enc, "info_rows", [0.0]), "info_rows, info_cols, info_vals sizes differ"),
    ]
    for args, match in cases:
        with pytest.raises(MessageError, match=match):
            decode_map(*args)


def test_unknown_segments_are_ignored_even_when_not_finite(rng):
    """Readers ignore labels they do not know (README, "Message layouts"): their values too."""
    enc = _enc(rng)
    labels = [*enc.labels, "future"]
    sizes = [*enc.sizes, 2]
    data = np.r_[enc.data, np.nan, np.inf]
    back = decode_map(labels, sizes, data)
    assert back.local_map.x.tobytes() == decode_map(enc.labels, enc.sizes, enc.data).local_map.x.tobytes()


def test_ids_a_double_cannot_carry_are_refused_when_encoding():
    from linear_slam_ros.core.local_map import LocalMap

    with pytest.raises(InvalidMapError, match=r"id 9007199254740993 is out of range \(\|id\| < 2\*\*53\)"):
        LocalMap(2, 0, None, np.array([2**53 + 1]), np.array([1], np.int8), np.zeros(2), np.eye(2))
    # a map the core built without validation (trusted): the encoder still refuses it
    m = LocalMap.trusted(2, 0, None, np.array([2**53 + 1]), np.array([1], np.int8), np.zeros(2), np.eye(2))
    with pytest.raises(MessageError, match="segment 'var_ids': value 9007199254740993 cannot be carried exactly"):
        encode_map(m, 1)
    with pytest.raises(MessageError, match="segment 'header': value 9007199254740992 cannot be carried exactly"):
        encode_map(m.replace(ids=np.array([1])), 2**53)


def test_map_message_information_errors():
    from linear_slam_ros.core.local_map import LocalMap

    m = LocalMap(2, 0, None, np.array([1]), np.array([1], np.int8), np.zeros(2), np.eye(2))
    enc = encode_map(m, 1)
    for rows, cols, vals, match in (
        ([0, 5], [0, 1], [1.0, 1.0], "information index out of range for a state of 2 values"),
        ([0, -1], [0, 0], [1.0, 1.0], "information index out of range for a state of 2 values"),  # negative
        ([0, 0], [0, 2], [1.0, 1.0], "information index out of range for a state of 2 values"),  # column n
        ([1, 0], [0, 1], [1.0, 1.0], "must be in the upper triangle"),
        ([0, 0], [0, 0], [1.0, 1.0], "repeated information entry"),
    ):
        labels, sizes, data = _mutate(enc, "info_rows", rows)
        enc2 = type(enc).of(labels, sizes, data)
        labels, sizes, data = _mutate(enc2, "info_cols", cols)
        enc3 = type(enc).of(labels, sizes, data)
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
    data = enc.data.copy()
    data[6] = 4.0  # header: frame_pose_id
    with pytest.raises(MessageError, match="a feature-only map's frame_pose_id and end_pose_id are -1 .* got 4 and -1"):
        decode_feature_map(enc.labels, enc.sizes, data)
    i = enc.labels.index("var_ids")
    data = enc.data.copy()
    first = sum(enc.sizes[:i])
    data[first + 1] = data[first]  # two variables with one id: positions() would keep one of them
    with pytest.raises(InvalidMapError, match=f"feature id {int(data[first])} is listed more than once"):
        decode_feature_map(enc.labels, enc.sizes, data)


# ---------------------------------------------------------------------------------------- input limits

REPO = Path(__file__).resolve().parents[2]


def _raw_map(n_features: int, vals=None, seq: int = 5):
    """The layout, sizes and data of a feature map message with diagonal information, built directly."""
    n = 2 * n_features
    segments = [
        ("header", [1, 2, 0, seq, 0, 0, 0, -1, 1]),
        ("var_ids", np.arange(1, n_features + 1)),
        ("var_kinds", np.ones(n_features)),
        ("state", np.zeros(n)),
        ("info_rows", np.arange(n)),
        ("info_cols", np.arange(n)),
        ("info_vals", np.full(n, 100.0) if vals is None else vals),
    ]
    arrays = [np.asarray(v, dtype=float) for _, v in segments]
    return [k for k, _ in segments], [a.size for a in arrays], np.concatenate(arrays)


def _raw_chunk(k: int, seq: int = 4, to=None):
    """The layout, sizes and data of a 2D star chunk of ``k`` edges from pose 0, built directly."""
    segments = [
        ("header", [1, 2, 2, seq, 0, 0, k]),
        ("edge_from", np.zeros(k)),
        ("edge_to", np.arange(1, k + 1) if to is None else to),
        ("measurement", np.tile([1.0, 0.0, 0.1], k)),
        ("information", np.tile(np.eye(3).ravel() * 100.0, k)),
    ]
    arrays = [np.asarray(v, dtype=float) for _, v in segments]
    return [s for s, _ in segments], [a.size for a in arrays], np.concatenate(arrays)


def _in_fresh_process(body: str, *helpers) -> dict:
    """Run ``body`` (which sets ``message`` and ``run``, and may call ``helpers``) in a new
    interpreter; return the seconds and the peak-RSS growth (MB, ``resource.getrusage``) of
    ``run()`` and the error it raised."""
    sources = "import numpy as np\n" + "".join(inspect.getsource(h) for h in helpers)
    script = sources + textwrap.dedent(body) + textwrap.dedent("""
        import json, resource, time
        before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
        t0 = time.perf_counter()
        try:
            run()
            error = None
        except Exception as exc:
            error = f"{type(exc).__name__}: {exc}"
        seconds = time.perf_counter() - t0
        growth = (resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - before) / 1024
        print(json.dumps({"seconds": seconds, "growth_mb": growth, "error": error}))
    """)
    result = subprocess.run([sys.executable, "-c", script], cwd=REPO, capture_output=True, text=True, timeout=300, check=False)
    assert result.returncode == 0, result.stderr[-2000:]
    return json.loads(result.stdout.strip().splitlines()[-1])


@pytest.mark.parametrize("limits, bound", [("None", 100_000), ("NODE_LIMITS", 5_000)])
def test_a_map_of_a_million_scalars_is_refused_from_its_sizes(limits, bound):
    """It used to be densified (7.28 TiB) by sequential joining; now its header and sizes refuse it."""
    out = _in_fresh_process(f"""
        from linear_slam_ros.core.limits import NODE_LIMITS
        from msg_adapters import decode_map
        message = _raw_map(500_000)
        def run():
            decode_map(*message, limits={limits})
    """, _raw_map)
    assert out["error"] == f"MessageError: map message seq 5: 1000000 state scalars, above the limit max_state_scalars = {bound}"
    assert out["seconds"] < 1.0 and out["growth_mb"] < 200


def test_a_chunk_of_100000_edges_is_refused_from_its_header():
    """It used to be made a dense block diagonal (671 GiB); now its header refuses it."""
    out = _in_fresh_process("""
        from msg_adapters import decode_chunk
        message = _raw_chunk(100_000)
        def run():
            decode_chunk(*message)
    """, _raw_chunk)
    assert out["error"] == "MessageError: pose_graph message seq 4: 100000 edges, above the limit max_chunk_edges = 10000"
    assert out["seconds"] < 1.0 and out["growth_mb"] < 200


def test_a_star_chunk_allowed_100000_edges_becomes_a_sparse_map_in_bounded_memory():
    """With limits raised to admit it, the star chunk's block-diagonal information is built sparse."""
    out = _in_fresh_process("""
        import scipy.sparse as sp
        from linear_slam_ros.core.limits import InputLimits
        from linear_slam_ros.pose_graph.chunks import chunk_to_local_map
        from msg_adapters import decode_chunk
        message = _raw_chunk(100_000)
        limits = InputLimits(max_chunk_edges=100_000, max_state_scalars=300_000)
        def run():
            local = chunk_to_local_map(decode_chunk(*message, limits=limits).graph, limits)
            assert local.state_dim == 300_000 and sp.issparse(local.info) and local.info.nnz == 300_000
    """, _raw_chunk)
    assert out["error"] is None
    assert out["seconds"] < 10.0 and out["growth_mb"] < 400


def test_map_size_limits_are_checked_before_decoding():
    small = InputLimits(max_state_scalars=10, max_info_triplets=8)
    decode_map(*_raw_map(4), limits=small)  # 8 scalars, 8 triplets: fine
    with pytest.raises(MessageError, match="^map message seq 5: 12 state scalars, above the limit max_state_scalars = 10$"):
        decode_map(*_raw_map(6), limits=small)
    match = "^map message seq 5: 10 information triplets \\(segment 'info_rows'\\), above the limit max_info_triplets = 8$"
    with pytest.raises(MessageError, match=match):
        decode_map(*_raw_map(5), limits=small)
    labels, sizes, data = _raw_map(1)
    header = data[:9]
    many_ids = (labels, [9, 11, 11, 2, 1, 1, 1], np.r_[header, np.arange(11), np.ones(11), 0, 0, 0, 0, 100])
    match = "^map message seq 5: 11 values in segment 'var_ids', above the limit max_state_scalars = 10$"
    with pytest.raises(MessageError, match=match):
        decode_map(*many_ids, limits=small)
    # more triplets than the upper triangle has entries: some repeat, whatever the limit
    repeated = (labels, [9, 1, 1, 2, 4, 4, 4], np.r_[header, 1, 1, 0, 0, [0, 0, 1, 0], [0, 1, 1, 0], [1, 0, 1, 1]])
    match = "^map message seq 5: 4 information triplets, more than the 3 entries of the upper triangle"
    with pytest.raises(MessageError, match=match):
        decode_map(*repeated)
    with pytest.raises(MessageError, match="negative segment size in layout \\[9, -1, 3"):
        decode_map(labels, [9, -1, 3, 2, 2, 2, 2], data)


def test_chunk_size_limits_are_checked_before_the_graph_is_built():
    limits = InputLimits(max_chunk_edges=3, max_state_scalars=6)
    decode_chunk(*_raw_chunk(2), limits=limits)
    with pytest.raises(MessageError, match="^pose_graph message seq 4: 4 edges, above the limit max_chunk_edges = 3$"):
        decode_chunk(*_raw_chunk(4), limits=limits)
    match = "^pose_graph message seq 4: 9 state scalars \\(the local map of a chunk over 4 poses\\), above the limit "
    with pytest.raises(MessageError, match=match + "max_state_scalars = 6$"):
        decode_chunk(*_raw_chunk(3), limits=limits)
    decode_chunk(*_raw_chunk(3, to=[1, 2, 1]), limits=limits)  # 3 poses: 6 scalars


@pytest.mark.parametrize(
    "value, match",
    [
        (1e300, "information diagonal entry 3 \\(feature 2\\) is 1e\\+300, above the limit max_information = 1e\\+12"),
        (1e-300, "information diagonal entry 3 \\(feature 2\\) is 1e-300, below the limit min_information = 1e-12"),
    ],
)
def test_map_information_magnitudes_are_rejected(value, match):
    with pytest.raises(InvalidMapError, match=f"^local map 'local map seq 5': {match}$"):
        decode_map(*_raw_map(2, vals=[100.0, 100.0, 100.0, value]))
    with pytest.raises(InvalidMapError, match=match):
        decode_map(*_raw_map(2, vals=[100.0, 100.0, 100.0, value]), limits=NODE_LIMITS)


def _state_message(x):
    m = LocalMap(2, 0, 1, np.array([1, 7]), np.array([0, 1], np.int8), np.array([1.0, 0.0, 0.1, 2.0, 1.0]), np.eye(5) * 100)
    return _mutate(encode_map(m, 3), "state", x)


def test_map_angles_and_coordinates_are_bounded():
    match = "^local map 'local map seq 3': angle at state index 2 \\(pose 1\\) is 1e\\+300 rad, beyond the limit "
    with pytest.raises(InvalidMapError, match=match + "max_angle = 10000 rad$"):
        decode_map(*_state_message([1.0, 0.0, 1e300, 2.0, 1.0]))
    match = "coordinate at state index 3 \\(feature 7\\) is -1e\\+300 m, beyond the limit max_coordinate = 1e\\+06 m$"
    with pytest.raises(InvalidMapError, match=match):
        decode_map(*_state_message([1.0, 0.0, 0.1, -1e300, 1.0]))
    decode_map(*_state_message([1.0, 0.0, 7.0, 2.0, 1.0]))  # an unwrapped angle is fine
    match = "angle at state index 2 \\(pose 1\\) is 7 rad, beyond the limit max_angle = 5 rad$"
    with pytest.raises(InvalidMapError, match=match):
        decode_map(*_state_message([1.0, 0.0, 7.0, 2.0, 1.0]), limits=InputLimits(max_angle=5.0))


def _mutate_enc(enc, segment, values):
    labels, sizes, data = _mutate(enc, segment, values)
    return type(enc).of(labels, sizes, data)


def _chunk_message(over):
    """A star chunk 3->4, 3->7 (seq 6) with entries overridden: ``{(edge, row, col): value}`` of the
    information, ``{(edge, -1, component): value}`` of the measurement."""
    info = np.stack([np.eye(3) * 100.0, np.eye(3) * 200.0])
    z = np.array([[1.0, 0.0, 0.1], [2.0, 1.0, -0.2]])
    for (edge, row, col), value in over.items():
        if row < 0:
            z[edge, col] = value
        else:
            info[edge, row, col] = value
    enc = encode_chunk(PoseGraph.from_edges([3, 3], [4, 7], np.ones((2, 3)), np.stack([np.eye(3)] * 2)), 6)
    return _mutate(_mutate_enc(enc, "measurement", z.ravel()), "information", info.ravel())


@pytest.mark.parametrize(
    "over, match",
    [
        ({(1, 2, 2): 1e300},
         "information of edge 1 \\(3->7\\): information diagonal entry 2 is 1e\\+300, above the limit max_information = 1e\\+12"),
        ({(0, 0, 0): 1e-300},
         "information of edge 0 \\(3->4\\): information diagonal entry 0 is 1e-300, below the limit min_information = 1e-12"),
        ({(1, -1, 2): 1e300},
         "measurement of edge 1 \\(3->7\\): angle 0 is 1e\\+300 rad, beyond the limit max_angle = 10000 rad"),
        ({(0, -1, 1): -1e300},
         "measurement of edge 0 \\(3->4\\): translation 1 is -1e\\+300 m, beyond the limit max_coordinate = 1e\\+06 m"),
        ({(0, 0, 0): 1e12, (0, 1, 1): 1e-3},
         "information of edge 0 \\(3->4\\): information matrix is too ill-conditioned to join in double precision: "
         "condition number 1e\\+15 \\(2-norm\\)"),
    ],
)
def test_chunk_numbers_are_bounded(over, match):
    with pytest.raises(GraphError, match=f"^pose-graph chunk 6: {match}"):
        decode_chunk(*_chunk_message(over))


def test_chunk_limits_reach_the_local_map_it_makes():
    """Fusing parallel edges adds their information: the map is checked with the same limits."""
    limits = InputLimits(max_information=250.0)
    z = np.array([[1.0, 0, 0.1], [1.2, 0, 0.1]])
    enc = encode_chunk(PoseGraph.from_edges([3, 3], [4, 4], z, np.stack([np.eye(3) * 200.0] * 2)), 2)
    chunk = decode_chunk(enc.labels, enc.sizes, enc.data, limits=limits)
    assert chunk_to_local_map(chunk.graph).info_dense()[0, 0] == 400.0  # default limits
    match = "^local map 'pose-graph chunk 2': information diagonal entry 0 \\(pose 4\\) is 400, above the limit "
    with pytest.raises(GraphError, match=match + "max_information = 250$"):
        chunk_to_local_map(chunk.graph, limits)


def test_feature_only_map_limits(rng):
    from msg_adapters import decode_feature_map, encode_feature_map

    fmap = _feature_map(2, rng)
    enc = encode_feature_map(fmap, 9)
    match = f"^map message seq 9: {fmap.x.size} state scalars, above the limit max_state_scalars = 10$"
    with pytest.raises(MessageError, match=match):
        decode_feature_map(enc.labels, enc.sizes, enc.data, limits=InputLimits(max_state_scalars=10))
    who = "^feature-only map 'feature-only map seq 9': "
    k = enc.labels.index("state")
    data = enc.data.copy()
    data[sum(enc.sizes[:k]) + 1] = 1e300
    with pytest.raises(InvalidMapError, match=who + "coordinate at state index 1 is 1e\\+300 m, beyond the limit max_coordinate"):
        decode_feature_map(enc.labels, enc.sizes, data)
    v = enc.labels.index("info_vals")
    data = enc.data.copy()
    data[sum(enc.sizes[:v])] = 1e300  # the first triplet is a diagonal entry (0, 0)
    with pytest.raises(InvalidMapError, match=who + "information diagonal entry 0 is 1e\\+300"):
        decode_feature_map(enc.labels, enc.sizes, data)


def test_decoded_sparse_maps_stay_sparse_and_equal_the_original():
    n = 2 * 150
    info = sp.diags([np.full(n, 50.0), np.full(n - 1, 1.0)], [0, 1])
    info = sp.csr_matrix(info + sp.triu(info, 1).T)
    m = LocalMap(2, 0, None, np.arange(1, 151), np.ones(150, np.int8), np.zeros(n), info, name="m")
    back = decode_map(*parts(to_msg(encode_map(m, 1)))).local_map
    assert sp.issparse(back.info) and (back.info != m.info).nnz == 0


def test_global_map_carries_its_islands_and_reads_earlier_statistics():
    from msg_adapters.global_map import encode_global
    from msg_adapters.layout import STATS_FIELDS

    world = make_world(2, 6, 8, np.random.default_rng(3))
    m = noisy_local_maps(world, np.random.default_rng(4), steps_per_map=3)[0]
    stats = {k: float(i) for i, k in enumerate(STATS_FIELDS)}
    enc = encode_global(m, 4, Stamp(), 5, stats, islands=[5, 2])
    decoded = decode_map(enc.labels, enc.sizes, enc.data)
    assert decoded.islands == (5, 2) and decoded.stats == stats and decoded.stats["n_islands"] == 7.0
    assert decode_map(*_without(enc, "islands")).islands is None
    # a stats segment of an earlier version (7 values, no n_islands) is read as far as it goes
    labels, sizes, data = _without(enc, "islands")
    i = labels.index("stats")
    start = sum(sizes[:i])
    old = decode_map(labels, sizes[:i] + (7,) + sizes[i + 1 :], np.concatenate([data[: start + 7], data[start + 8 :]]))
    assert old.stats == {k: stats[k] for k in STATS_FIELDS[:7]}
    bad = np.concatenate([enc.data[:-1], [2.5]])
    with pytest.raises(MessageError, match="segment 'islands' must hold integers"):
        decode_map(enc.labels, enc.sizes, bad)


def _without(enc, label: str) -> tuple[tuple[str, ...], tuple[int, ...], np.ndarray]:
    """The segments of an encoded message without ``label``."""
    i = enc.labels.index(label)
    start = sum(enc.sizes[:i])
    data = np.concatenate([enc.data[:start], enc.data[start + enc.sizes[i] :]])
    return enc.labels[:i] + enc.labels[i + 1 :], enc.sizes[:i] + enc.sizes[i + 1 :], data
