"""LocalMap validation: every invariant has an error naming the map and the fault."""

from __future__ import annotations

import pickle

import numpy as np
import pytest
import scipy.sparse as sp

from linear_slam_ros.core.errors import InvalidMapError
from linear_slam_ros.core.local_map import FEATURE, POSE, LocalMap, angle_mask, block_diagonal


def _good(**over):
    kw = dict(
        dim=2,
        frame_id=0,
        end_id=1,
        ids=np.array([1, 7]),
        kinds=np.array([POSE, FEATURE], dtype=np.int8),
        x=np.array([1.0, 0.0, 0.1, 2.0, 3.0]),
        info=np.eye(5) * 10,
        name="lm",
    )
    kw.update(over)
    return LocalMap(**kw)


def test_valid_map_layout():
    m = _good()
    assert m.state_dim == 5 and m.n_vars == 2
    np.testing.assert_array_equal(m.offsets, [0, 3])
    assert m.has_pose(1) and not m.has_pose(7)
    np.testing.assert_array_equal(m.pose(1), [1.0, 0.0, 0.1])
    np.testing.assert_array_equal(m.pose(0), [0.0, 0.0, 0.0])
    np.testing.assert_array_equal(m.angles, [False, False, True, False, False])
    np.testing.assert_array_equal(m.scalar_index([1]), [3, 4])
    assert m.info_nnz() == 5


def test_sparse_information_is_accepted():
    assert _good(info=sp.csr_matrix(np.eye(5) * 3)).info_nnz() == 5


@pytest.mark.parametrize(
    "over, match",
    [
        (dict(dim=4), "'lm': dimension must be 2 or 3, got 4"),
        (dict(kinds=np.array([POSE], dtype=np.int8)), "ids and kinds must be 1-D of equal length"),
        (dict(kinds=np.array([POSE, 5], dtype=np.int8)), "variable kind must be 0 \\(pose\\) or 1 \\(feature\\), got 5"),
        (dict(ids=np.array([-1, 7])), "pose ids must be >= 0, got -1"),
        # 2 id + kind overflowed an int64 at 2**62 (review of session 26): bounded as the messages carry ids
        (dict(ids=np.array([2**62, 7])), "'lm': id 4611686018427387904 is out of range \\(\\|id\\| < 2\\*\\*53\\)"),
        (dict(ids=np.array([0, -(2**53)])), "'lm': id -9007199254740992 is out of range"),
        (dict(frame_id=2**53), "'lm': id 9007199254740992 is out of range"),
        (
            dict(ids=np.array([1, 1]), kinds=np.array([POSE, POSE], dtype=np.int8), x=np.zeros(6), info=np.eye(6)),
            "duplicate variable pose 1",
        ),
        (dict(frame_id=1, end_id=None), "frame pose 1 is also a variable"),
        (dict(end_id=9), "end pose 9 is neither the frame pose nor a pose of the map"),
        (dict(x=np.zeros(4)), "state has shape \\(4,\\), the variables need \\(5,\\)"),
        (dict(info=np.eye(4)), "information matrix has shape \\(4, 4\\), expected \\(5, 5\\)"),
        (dict(x=np.array([1.0, np.nan, 0, 0, 0])), "state entry 1 is not finite"),
        (dict(info=np.diag([1.0, 1, 1, 1, np.inf])), "non-finite entries"),
        (dict(info=np.eye(5) + np.triu(np.ones((5, 5)), 1)), "not symmetric"),
        (dict(info=np.diag([1.0, 1, 1, 1, -1])), "not positive definite"),
        (
            dict(dim=3, kinds=np.array([POSE, POSE], dtype=np.int8), x=np.r_[0, 0, 0, 0.1, 0.2, 0.3, 1, 2, 3, 0.4, -np.pi / 2, 2],
                 info=np.eye(12)),
            r"map 'lm': pose 7 \(state index 10\) in the frame of pose 0 has pitch at \+-90 deg \(\|cos beta\| = 6.1\d+e-17",
        ),
    ],
)
def test_each_invariant_is_checked(over, match):
    with pytest.raises(InvalidMapError, match=match):
        _good(**over)


def test_large_sparse_not_spd_is_rejected():
    n = 3001 * 2
    ids = np.arange(1, 3002)
    diag = np.ones(n)
    diag[-1] = -1.0
    with pytest.raises(InvalidMapError, match="not positive definite"):
        LocalMap(2, 0, None, ids, np.full(3001, FEATURE, np.int8), np.zeros(n), sp.diags(diag).tocsr(), name="big")


def test_angle_mask_3d():
    mask = angle_mask(3, np.array([POSE, FEATURE], dtype=np.int8))
    np.testing.assert_array_equal(np.flatnonzero(mask), [3, 4, 5])


def test_pose_lookup_error_names_the_map():
    with pytest.raises(KeyError, match="pose 5 is not in map 'lm'"):
        _good().pose(5)


def test_block_diagonal_equals_scipys_block_diag(rng):
    """Dense blocks (zeros left out), sparse ones (stored entries kept, duplicates summed, unsorted
    indices sorted), a base to extend and empty blocks: the same canonical CSR as scipy's."""
    dense = rng.standard_normal((4, 4))
    dense[1, 2] = 0.0
    unsorted = sp.csr_matrix((np.array([1.0, 2.0, 3.0, 0.0]), np.array([2, 0, 1, 1]), np.array([0, 2, 3, 4])), shape=(3, 3))
    unsorted.has_sorted_indices = False
    duplicated = sp.coo_matrix((np.array([1.0, 2.0]), (np.array([0, 0]), np.array([1, 1]))), shape=(2, 2))
    blocks = [dense, unsorted, sp.csr_matrix((0, 0)), duplicated, np.eye(1) * 5.0]
    base = sp.random(5, 5, density=0.4, random_state=1, format="csr")
    for b in (None, base):
        got = block_diagonal(blocks, b)
        parts = ([] if b is None else [b]) + [sp.csr_matrix(x) if not sp.issparse(x) else x for x in blocks]
        want = sp.block_diag(parts, format="csr")
        want.sum_duplicates()
        assert got.shape == want.shape and got.has_canonical_format
        np.testing.assert_array_equal(got.indptr, want.indptr)
        np.testing.assert_array_equal(got.indices, want.indices)
        np.testing.assert_array_equal(got.data, want.data)
        assert got.indices.dtype == np.int32
    assert block_diagonal([]).shape == (0, 0)


@pytest.mark.parametrize("info", [np.eye(5) * 10, sp.csr_matrix(np.eye(5) * 3)])
@pytest.mark.parametrize("end_id", [1, None])
def test_a_map_pickles_its_fields_and_not_its_caches(info, end_id):
    """What goes to the refiner's process: the same map on the other side, its layout and lookups rebuilt there."""
    m = _good(info=info, end_id=end_id)
    assert m.key_set and m.offsets.size  # cached on this side
    back = pickle.loads(pickle.dumps(m, protocol=pickle.HIGHEST_PROTOCOL))
    assert isinstance(back, LocalMap) and back is not m
    assert (back.dim, back.frame_id, back.end_id, back.name) == (m.dim, m.frame_id, m.end_id, m.name)
    for field in ("ids", "kinds", "x"):
        np.testing.assert_array_equal(getattr(back, field), getattr(m, field))
        assert getattr(back, field).dtype == getattr(m, field).dtype
    assert sp.issparse(back.info) == sp.issparse(m.info)
    np.testing.assert_array_equal(sp.csr_matrix(back.info).toarray(), sp.csr_matrix(m.info).toarray())
    assert "key_set" not in vars(back) and back.layout is not m.layout
    assert back.key_set == m.key_set
    np.testing.assert_array_equal(back.offsets, m.offsets)


def test_a_pose_close_to_the_pitch_lock_is_accepted():
    x = np.r_[0, 0, 0, 0.1, np.pi / 2 - 2e-6, 0.3, 1, 2, 3, 0.4, -np.pi / 2 + 2e-6, 2]
    m = _good(dim=3, kinds=np.array([POSE, POSE], dtype=np.int8), x=x, info=np.eye(12))
    assert m.pitch_lock_fault() is None


@pytest.mark.parametrize("sparse", [False, True])
def test_3d_euler_triples_are_made_canonical_on_construction(sparse, rng):
    """``(alpha + pi, pi - beta, gamma + pi)`` is the same rotation; the map gets the canonical triple (pitch within
    +-pi/2) and its information the ``beta`` row and column negated (exact: the change is affine). The caller's
    arrays are left as they were."""
    from linear_slam_ros.core.geometry import canonical_angles3, rot3

    a = rng.normal(size=(12, 12))
    info = a @ a.T + 12 * np.eye(12)
    x = np.array([1.0, 2.0, 3.0, 0.3, 2.0, -0.4, 4.0, 5.0, 6.0, 0.1, 0.2, 0.3])  # pose 5: pitch 2.0 > pi/2
    given_x, given_info = x.copy(), info.copy()
    ids, kinds = np.array([5, 6]), np.array([POSE, POSE], dtype=np.int8)
    m = LocalMap(3, 0, 6, ids, kinds, x, sp.csr_matrix(info) if sparse else info, name="lm")
    np.testing.assert_allclose(m.x[3:6], [0.3 - np.pi, np.pi - 2.0, -0.4 + np.pi], atol=1e-15)
    np.testing.assert_array_equal(m.x[[0, 1, 2, 6, 7, 8, 9, 10, 11]], x[[0, 1, 2, 6, 7, 8, 9, 10, 11]])
    np.testing.assert_allclose(rot3(m.x[3:6]), rot3(x[3:6]), atol=1e-15)
    flip = np.diag([1.0] * 4 + [-1.0] + [1.0] * 7)
    np.testing.assert_allclose(m.info_dense(), flip @ info @ flip, rtol=1e-15)
    assert sp.issparse(m.info) == sparse
    np.testing.assert_array_equal(x, given_x)
    np.testing.assert_array_equal(info, given_info)
    angles, changed = canonical_angles3(np.array([[0.1, -1.7 - 2 * np.pi, 0.2], [0.1, 1.5, 0.2], [3.0, 1.5707, -3.0]]))
    assert changed.tolist() == [True, False, False]
    np.testing.assert_allclose(rot3(angles[0]), rot3(np.array([0.1, -1.7, 0.2])), atol=1e-14)
    assert abs(angles[0, 1]) <= np.pi / 2


def test_pose_graph_measurements_are_made_canonical():
    from linear_slam_ros.core.geometry import rot3
    from linear_slam_ros.pose_graph.graph import PoseGraph

    z = np.array([[1.0, 0.0, 0.0, 0.5, 2.5, 0.1], [1.0, 0.0, 0.0, 0.5, 0.5, 0.1]])
    info = np.stack([np.eye(6) + 0.1, np.eye(6) + 0.2])
    graph = PoseGraph.from_edges([0, 1], [1, 2], z, info)
    np.testing.assert_allclose(rot3(graph.measurements[0, 3:]), rot3(z[0, 3:]), atol=1e-15)
    assert abs(graph.measurements[0, 4]) <= np.pi / 2
    np.testing.assert_array_equal(graph.measurements[1], z[1])
    flip = np.diag([1.0, 1, 1, 1, -1, 1])
    np.testing.assert_allclose(graph.information[0], flip @ info[0] @ flip)
    np.testing.assert_array_equal(graph.information[1], info[1])
    assert z[0, 4] == 2.5 and info[0, 4, 0] == 0.1  # the caller's arrays


def test_an_asymmetric_sparse_information_is_refused():
    info = sp.csr_matrix(np.eye(5) * 3.0)
    info = info.tolil()
    info[0, 3] = 0.5  # one entry without its mirror
    with pytest.raises(InvalidMapError, match="not symmetric"):
        LocalMap(2, 0, 7, np.array([7, 1]), np.array([POSE, 1], dtype=np.int8), np.zeros(5), info.tocsr(), name="lm")


def test_block_diagonal_equals_scipy_s_block_diag_for_runs_of_dense_and_sparse_blocks(rng):
    """Runs of dense blocks are assembled at once: the same arrays as scipy's block_diag, zeros left out."""
    blocks: list = []
    for k in range(40):
        size = int(rng.integers(1, 7))
        dense = rng.standard_normal((size, size))
        dense[rng.random((size, size)) < 0.3] = 0.0  # zeros inside the blocks, whole zero rows too
        if k % 9 == 0:
            dense[0] = 0.0
        blocks.append(sp.csr_matrix(dense) if k % 7 == 3 else dense if k % 5 else dense.T)  # transposed views too
    base = sp.random(5, 5, density=0.4, random_state=1, format="csr")
    for given_base in (None, base, base.toarray()):
        got = block_diagonal(blocks, given_base)
        parts = ([] if given_base is None else [given_base]) + blocks
        expected = sp.block_diag([sp.csr_matrix(b) for b in parts], format="csr")
        expected.eliminate_zeros()
        expected.sort_indices()
        np.testing.assert_array_equal(got.indptr, expected.indptr)
        np.testing.assert_array_equal(got.indices, expected.indices)
        np.testing.assert_array_equal(got.data, expected.data)
    assert block_diagonal([]).shape == (0, 0) and block_diagonal([np.zeros((2, 2))]).nnz == 0
