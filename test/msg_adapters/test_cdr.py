"""The CDR writer of ``Float64MultiArray`` (``msg_adapters.cdr``), the segments it writes
(``Encoded``) and the information's upper triangle (``upper_triplets``)."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp
from rclpy.serialization import deserialize_message, serialize_message
from std_msgs.msg import Float64MultiArray

from linear_slam_ros.core.errors import MessageError
from msg_adapters.bags import serialize
from msg_adapters.cdr import ENCAPSULATION_CDR_LE, to_cdr
from msg_adapters.layout import Encoded, upper_triplets
from msg_adapters.ros import to_msg

LABEL_SETS = [
    (), ("a",), ("abc", "header", "xy"), ("ab", "abcdefg", "abcd"), ("abcdefghijk",), ("header", "var_ids", "info_rows"),
]


@pytest.mark.parametrize("labels", LABEL_SETS)
def test_to_cdr_is_what_rosbags_writes_and_rclpy_reads(labels, rng):
    for _ in range(4):
        sizes = tuple(int(s) for s in rng.integers(0, 5, len(labels)))
        enc = Encoded.of(labels, sizes, rng.standard_normal(sum(sizes)))
        ours = to_cdr(enc).tobytes()
        assert ours[:4] == ENCAPSULATION_CDR_LE
        assert deserialize_message(ours, Float64MultiArray) == to_msg(enc)
        assert len(ours) == len(serialize_message(to_msg(enc)))  # rclpy's, whose padding bytes are unset
        if sum(sizes):  # rosbags leaves out the alignment of an empty data sequence; otherwise the same bytes
            assert ours == serialize(enc)


def test_to_cdr_converts_integer_parts_exactly_into_aligned_values():
    rows = np.array([0, 1, 2**31 - 1], dtype=np.int32)
    ids = np.array([-(2**53), 7], dtype=np.int64)
    kinds = np.array([0, 1, 1], dtype=np.int8)
    enc = Encoded(("var_ids", "var_kinds", "info_rows"), (ids, kinds, rows))
    buffer = to_cdr(enc)
    values = np.frombuffer(buffer.tobytes()[-8 * 8 :], dtype=np.float64)
    np.testing.assert_array_equal(values, np.concatenate([ids, kinds, rows]).astype(np.float64))
    data_start = buffer.size - 8 * 8
    assert (buffer.ctypes.data + data_start) % 8 == 0  # the values are aligned in memory
    assert (data_start - 4) % 8 == 0  # and in the CDR stream
    assert buffer.tobytes() == serialize(enc)


def test_encoded_splits_and_concatenates_its_segments(rng):
    data = rng.standard_normal(7)
    enc = Encoded.of(("a", "b", "c"), (3, 0, 4), data)
    assert enc.sizes == (3, 0, 4)
    np.testing.assert_array_equal(enc.parts[0], data[:3])
    np.testing.assert_array_equal(enc.data, data)
    assert enc.data is enc.data  # made once
    mixed = Encoded(("i", "f"), (np.arange(3, dtype=np.int32), np.ones(2)))
    assert mixed.data.dtype == np.float64 and mixed.data.tolist() == [0.0, 1.0, 2.0, 1.0, 1.0]
    assert Encoded((), ()).data.size == 0


def test_encoded_errors():
    with pytest.raises(MessageError, match=r"2 labels for 1 parts"):
        Encoded(("a", "b"), (np.zeros(2),))
    with pytest.raises(MessageError, match=r"segment\(s\) \['m'\] are not 1-D"):
        Encoded(("v", "m"), (np.zeros(2), np.zeros((2, 2))))
    with pytest.raises(MessageError, match=r"sizes \[2, 2\] add up to 4 values but data has 5"):
        Encoded.of(("a", "b"), (2, 2), np.zeros(5))


@pytest.mark.parametrize("n, density", [(0, 0.0), (1, 1.0), (6, 0.5), (40, 0.1)])
def test_upper_triplets_are_scipy_triu_in_the_same_order(n, density, rng):
    a = sp.random(n, n, density=density, random_state=np.random.RandomState(3), format="csr") if n else sp.csr_matrix((0, 0))
    info = (a + a.T).tocsr()
    expected = sp.triu(info, format="coo")
    for given in (info, info.toarray(), info.tocsc()):
        rows, cols, vals = upper_triplets(given)
        np.testing.assert_array_equal(rows, expected.row)
        np.testing.assert_array_equal(cols, expected.col)
        np.testing.assert_array_equal(vals, expected.data)
