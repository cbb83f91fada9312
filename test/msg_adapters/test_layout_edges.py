"""The array layout at its boundaries: end pose 0, kinds that wrap, short headers, dimension 1, NaN stats, id
2^53, second 2^31-1. (Found by a mutation audit: each test fails on a mutant the suite let through.)
"""

from __future__ import annotations

import numpy as np
import pytest

from linear_slam_ros.core.errors import InvalidMapError, MessageError
from linear_slam_ros.core.local_map import POSE, LocalMap
from msg_adapters.layout import MAP_KIND_GLOBAL, Stamp, decode_map, encode_map


def _map(end=0):
    return LocalMap(2, 5, end, np.array([0, 1]), np.array([POSE, POSE], np.int8), np.arange(6) * 0.1, np.eye(6) * 3.0)


def _msg(enc, label=None, value=None):
    parts = [np.asarray(p, float) for p in enc.parts]
    if label is not None:
        parts[enc.labels.index(label)] = np.asarray(value, float)
    return list(enc.labels), [p.size for p in parts], np.concatenate(parts)


def test_end_pose_zero_round_trips():
    assert decode_map(*_msg(encode_map(_map(0), 1))).local_map.end_id == 0


def test_a_kind_that_wraps_to_int8_is_refused():
    with pytest.raises(InvalidMapError):
        decode_map(*_msg(encode_map(_map(), 1), "var_kinds", [256.0, 0.0]))


def test_a_header_one_value_short_is_a_message_error():
    enc = encode_map(_map(), 1)
    with pytest.raises(MessageError, match="header has 8 values"):
        decode_map(*_msg(enc, "header", np.asarray(enc.parts[0], float)[:8]))


def test_dimension_1_is_refused():
    enc = encode_map(_map(), 1)
    h = np.asarray(enc.parts[0], float).copy()
    h[1] = 1
    with pytest.raises(MessageError, match="dimension must be 2 or 3"):
        decode_map(*_msg(enc, "header", h))


def test_nan_in_stats_is_refused():
    enc = encode_map(_map(), 1, map_kind=MAP_KIND_GLOBAL, stats={"n_joined": 1.0})
    s = np.asarray(enc.parts[enc.labels.index("stats")], float).copy()
    s[0] = np.nan
    with pytest.raises(MessageError, match="non-finite"):
        decode_map(*_msg(enc, "stats", s))


def test_the_largest_int32_second_is_a_valid_stamp():
    enc = encode_map(_map(), 1, Stamp(2**31 - 1, 0))
    assert decode_map(*_msg(enc)).stamp.sec == 2**31 - 1


def test_an_id_of_2_pow_53_is_refused():
    enc = encode_map(_map(), 1)
    with pytest.raises(MessageError, match="must hold integers"):
        decode_map(*_msg(enc, "var_ids", [2.0**53, 1.0]))
