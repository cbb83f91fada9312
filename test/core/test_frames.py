"""Closed-form change of frame: round trips, Jacobians, information transport (eq. 20)."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp

from linear_slam_ros.core.errors import FrameError, GeometryError
from linear_slam_ros.core.frames import change_frame, frame_layout, reframe, reframe_jacobian, transform_information
from linear_slam_ros.core.geometry import angles3, rot3
from linear_slam_ros.core.local_map import POSE, LocalMap
from linear_slam_ros.evaluation.synthetic import exact_local_maps, make_world
from linear_slam_ros.joining.sequential import CovarianceMap


def _map(dim, rng, poses_per_map=4):
    world = make_world(dim, 12, 15, rng)
    return exact_local_maps(world, rng, poses_per_map=poses_per_map, sensor_range=8.0)[1]


@pytest.mark.parametrize("dim", [2, 3])
def test_round_trip_restores_state_and_information(dim, rng):
    m = _map(dim, rng)
    other = int(m.pose_ids[0])
    there = change_frame(m, other)
    assert there.frame_id == other and there.has_pose(m.frame_id)
    back = change_frame(there, m.frame_id)
    np.testing.assert_array_equal(back.ids, m.ids)
    np.testing.assert_allclose(back.x, m.x, atol=1e-12)
    np.testing.assert_allclose(back.info_dense(), m.info_dense(), rtol=1e-10, atol=1e-8)


@pytest.mark.parametrize("dim", [2, 3])
def test_reframe_jacobian_against_finite_differences(dim, rng):
    m = _map(dim, rng)
    layout = frame_layout(dim, m.kinds, 1)
    jac = reframe_jacobian(dim, m.x, layout).dense(m.state_dim)
    numeric = np.zeros_like(jac)
    for k in range(m.state_dim):
        dx = np.zeros(m.state_dim)
        dx[k] = 1e-6
        numeric[:, k] = (reframe(dim, m.x + dx, layout) - reframe(dim, m.x - dx, layout)) / 2e-6
    np.testing.assert_allclose(jac, numeric, atol=1e-6)
    sparse = reframe_jacobian(dim, m.x, layout).csr(m.state_dim)
    np.testing.assert_allclose(sparse.toarray(), jac, atol=0)


@pytest.mark.parametrize("dim", [2, 3])
def test_forward_and_reverse_jacobians_are_inverse(dim, rng):
    m = _map(dim, rng)
    layout = frame_layout(dim, m.kinds, 0)
    x_new = reframe(dim, m.x, layout)
    h = reframe_jacobian(dim, m.x, layout).dense(m.state_dim)
    g = reframe_jacobian(dim, x_new, layout).dense(m.state_dim)
    np.testing.assert_allclose(g @ h, np.eye(m.state_dim), atol=1e-10)


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("slot", [0, 3])
def test_information_transport_dense_and_sparse_agree(dim, slot, rng):
    m = _map(dim, rng, poses_per_map=6)
    layout = frame_layout(dim, m.kinds, slot)
    back = reframe_jacobian(dim, reframe(dim, m.x, layout), layout)
    dense = transform_information(m.info_dense(), back)
    info = sp.csr_matrix(m.info_dense())
    sparse = transform_information(info, back)
    np.testing.assert_allclose(sparse.toarray(), dense, rtol=1e-12, atol=1e-9)
    g = back.dense(m.state_dim)
    np.testing.assert_allclose(dense, g.T @ m.info_dense() @ g, rtol=1e-12, atol=1e-9)
    # the sparse result is canonical CSR (sorted, no duplicates): the form the joins assemble from
    assert isinstance(sparse, sp.csr_matrix) and sparse.has_canonical_format
    canonical = sparse.copy()
    canonical.sum_duplicates()
    np.testing.assert_array_equal(canonical.indices, sparse.indices)
    # the Jacobian is its block-diagonal part plus the slot's dense columns
    split = back.block_diagonal(m.state_dim).toarray()
    split[:, layout.frame_cols] += back.column(m.state_dim)
    np.testing.assert_array_equal(split, g)
    transposed = back.block_diagonal(m.state_dim, transpose=True).toarray()
    np.testing.assert_array_equal(transposed, back.block_diagonal(m.state_dim).toarray().T)


def test_sparse_transport_of_a_map_moved_before(rng):
    """A map whose information already holds dense rows (an earlier slot) moves again exactly."""
    m = _map(3, rng, poses_per_map=6)
    moved = change_frame(m, int(m.pose_ids[2]))
    sparse = change_frame(moved.replace(info=sp.csr_matrix(moved.info_dense())), int(m.pose_ids[4]))
    dense = change_frame(moved.replace(info=moved.info_dense()), int(m.pose_ids[4]))
    np.testing.assert_allclose(sparse.info_dense(), dense.info_dense(), rtol=1e-12, atol=1e-9)
    np.testing.assert_allclose(sparse.x, dense.x, atol=1e-12)


def test_same_frame_is_identity(rng):
    m = _map(2, rng)
    assert change_frame(m, m.frame_id) is m


def test_unknown_frame_pose_is_rejected(rng):
    m = _map(2, rng)
    with pytest.raises(FrameError, match="to the frame of pose 999: that pose is not in the map"):
        change_frame(m, 999)


def _pitched_map() -> LocalMap:
    """A 3D map in the frame of pose 0 whose pose 2 is pitched by exactly -90 deg from pose 1 (the
    map itself is fine: each is about 45 deg from its frame)."""
    x = np.array([1.0, 0.2, 0.3, 0.3, np.pi / 4, 0.1, 2.0, 0.5, 0.1, 0.3, -np.pi / 4, 0.1])
    info = np.eye(12) * 100 + np.diag(np.full(11, 1.0), 1) + np.diag(np.full(11, 1.0), -1)
    # the rotations chosen so that R_2 R_1^T has pitch -90 deg
    rot_1 = rot3(x[3:6])
    x[9:12] = angles3(rot3(np.array([0.7, -np.pi / 2, 0.0])) @ rot_1)
    return LocalMap(3, 0, 2, np.array([1, 2]), np.array([POSE, POSE]), x, info, "pitched")


def test_a_change_of_frame_that_puts_a_pose_at_pitch_90_deg_is_refused():
    m = _pitched_map()
    with pytest.raises(GeometryError, match=r"map 'pitched': pose 2 \(state index 10\) in the frame of pose 1 has pitch at"):
        change_frame(m, 1)
    assert change_frame(m, 2).frame_id == 2  # R_1 R_2^T is not at the lock (Euler pitch is not symmetric)
    covariance = CovarianceMap.from_local_map(m, name="pitched")
    before = covariance.cov_tilde.copy()
    with pytest.raises(GeometryError, match=r"map 'pitched': pose 2 \(state index 10\) in the frame of pose 1 has pitch"):
        covariance.change_frame(1, _in_place=True)
    np.testing.assert_array_equal(covariance.cov_tilde, before)  # refused before anything was changed


def test_a_map_not_positive_definite_in_the_frame_of_its_end_pose_cannot_be_joined():
    """Heading information 1e-3 and position information 1e10, 100 m away: condition 1e13 in its own
    frame, within the input bound, but not positive definite in double precision in its end pose's
    frame, where joins express it."""
    from linear_slam_ros.core.frames import end_frame_fault

    def far(distance, info):
        return LocalMap(2, 12, 13, np.array([13]), np.array([POSE], dtype=np.int8), np.array([distance, 0.0, 0.0]),
                        np.diag(info), "far")

    fault = end_frame_fault(far(100.0, [1e10, 1e10, 1e-3]))
    assert fault == ("local map 'far' in the frame of its end pose 13 (where it is joined): "
                     "information matrix is not positive definite")
    # a front-end's far pose with a sane heading: 1 km away, heading std 0.1 rad, position std 1 cm (condition 1e14
    # there: its position across the lever arm follows its heading; positive definite)
    assert end_frame_fault(far(1000.0, [1e4, 1e4, 100.0])) is None
    assert end_frame_fault(_map(2, np.random.default_rng(3))) is None


def test_a_moved_map_forgets_its_new_frame_pose_and_wraps_its_2d_headings():
    """Mutation audit (session 26): nothing checked that the new frame pose leaves the key lookup, nor that the
    moved 2D headings are wrapped into (-pi, pi] as documented."""
    from linear_slam_ros.core.local_map import pose_key

    m = LocalMap(2, 0, 5, np.array([3, 5]), np.array([POSE, POSE], np.int8), np.array([1.0, 0, 0.2, 2.0, 1.0, 7.0]),
                 np.eye(6) * 10, "m")
    moved = change_frame(m, 5)
    assert moved.frame_id == 5 and not moved.has_pose(5) and moved.index_of(pose_key(5)) is None
    assert moved.has_pose(0) and moved.ids.tolist() == [3, 0]
    headings = moved.x[moved.angles]
    assert np.all((headings > -np.pi) & (headings <= np.pi))
    np.testing.assert_allclose(headings, [np.mod(0.2 - 7.0 + np.pi, 2 * np.pi) - np.pi, np.mod(-7.0 + np.pi, 2 * np.pi) - np.pi])
