"""Exact sequential joining in covariance form equals the paper's information-form recursion."""

from __future__ import annotations

import numpy as np
import pytest

from linear_slam_ros.core.errors import FrameError, InvalidMapError, SolverError
from linear_slam_ros.evaluation.synthetic import exact_pose_graph_maps, make_world, noisy_local_maps
from linear_slam_ros.joining.sequential import (
    MIRROR_BLOCK,
    CovarianceMap,
    SequentialState,
    _mirror_lower,
    _sym_columns,
    sequential_step,
)
from support import join_sequential, join_sequential_information


@pytest.mark.parametrize("dim", [2, 3])
def test_covariance_form_equals_information_form(dim, rng):
    world = make_world(dim, 24, 30, rng, loops=1.2)
    maps = noisy_local_maps(world, rng, steps_per_map=2)
    fast = join_sequential(maps)
    literal = join_sequential_information(maps)
    np.testing.assert_array_equal(fast.ids, literal.ids)
    np.testing.assert_allclose(fast.x, literal.x, atol=1e-9)
    scale = np.abs(literal.info_dense()).max()
    np.testing.assert_allclose(fast.info_dense() / scale, literal.info_dense() / scale, atol=1e-9)


def test_covariance_form_on_pose_graphs_with_loops(rng):
    world = make_world(2, 30, 0, rng, loops=1.4)
    maps = exact_pose_graph_maps(world, rng, loop_every=3, loop_span=5)
    maps = [m.replace(x=m.x + rng.normal(scale=0.02, size=m.state_dim)) for m in maps]
    fast = join_sequential(maps)
    literal = join_sequential_information(maps)
    np.testing.assert_allclose(fast.x, literal.x, atol=1e-9)


def test_covariance_map_frame_change_round_trip(rng):
    world = make_world(3, 12, 15, rng)
    maps = noisy_local_maps(world, rng, steps_per_map=3)
    state = SequentialState()
    for m in maps:
        state = sequential_step(state, m)
    g = state.global_map
    there = g.change_frame(0)
    back = there.change_frame(g.frame_id)
    np.testing.assert_allclose(back.x, g.x, atol=1e-10)
    np.testing.assert_allclose(back.cov, g.cov, atol=1e-10)
    assert CovarianceMap.from_local_map(g.to_local_map()).cov == pytest.approx(g.cov, abs=1e-9)


def test_step_is_pure_and_rejects_a_foreign_frame(rng):
    world = make_world(2, 16, 12, rng)
    maps = noisy_local_maps(world, rng, steps_per_map=2)
    state = sequential_step(sequential_step(SequentialState(), maps[0]), maps[1])
    snapshot = (state.global_map.x.copy(), state.global_map.cov.copy())
    with pytest.raises(
        FrameError, match="submap 'noisy_5' is in the frame of pose 8, which is not in the global map \\(frame pose 4\\)"
    ):
        sequential_step(state, maps[4])
    sequential_step(state, maps[2])  # a successful step leaves the input state untouched too
    np.testing.assert_array_equal(state.global_map.x, snapshot[0])
    np.testing.assert_array_equal(state.global_map.cov, snapshot[1])
    assert state.n_joined == 2


def test_dimension_mismatch_and_empty_input(rng):
    m2 = noisy_local_maps(make_world(2, 6, 6, rng), rng, 2)
    m3 = noisy_local_maps(make_world(3, 6, 6, rng), rng, 2)
    state = sequential_step(SequentialState(), m2[0])
    with pytest.raises(InvalidMapError, match="submap 'noisy_2' is 3D, the global map is 2D"):
        sequential_step(state, m3[1])
    with pytest.raises(InvalidMapError, match="no local maps to join"):
        join_sequential([])
    with pytest.raises(FrameError, match="pose 99 is not in the global map"):
        state.global_map.change_frame(99)


def _joined_3d(rng):
    world = make_world(3, 12, 10, rng)
    state = SequentialState()
    for m in noisy_local_maps(world, rng, steps_per_map=3):
        state = sequential_step(state, m)
    return state.global_map


def test_factor_q_applied_in_every_mode_equals_its_dense_block(rng):
    g = _joined_3d(rng)
    q = g.q_block(np.arange(g.n_vars))
    gram = g.ang_blocks @ g.ang_blocks.transpose(0, 2, 1)
    assert np.abs(gram - np.eye(3)).max() > 1e-3  # the angle blocks are not even rotations
    for width in (4, 80):  # a product over all blocks at once, and matmul's stacked loop
        mat = rng.normal(size=(g.state_dim, width))
        np.testing.assert_allclose(g._apply_q(mat), q @ mat, atol=1e-12)
        np.testing.assert_allclose(g._apply_q(mat, transpose=True), q.T @ mat, atol=1e-12)
        np.testing.assert_allclose(g._apply_q(mat, inverse=True), np.linalg.solve(q, mat), atol=1e-10)
        np.testing.assert_allclose(g._apply_q(mat, inverse=True, transpose=True), np.linalg.solve(q.T, mat), atol=1e-10)
    some = np.array([0, 2, 3, g.n_vars - 1])
    np.testing.assert_allclose(g.q_block(some, inverse=True), np.linalg.inv(g.q_block(some)), atol=1e-10)


def test_q_block_in_2d_has_unit_angle_blocks_and_its_inverse_is_its_transpose(rng):
    state = SequentialState()
    for m in noisy_local_maps(make_world(2, 8, 8, rng), rng, 2):
        state = sequential_step(state, m)
    g = state.global_map
    q = g.q_block(np.arange(g.n_vars))
    np.testing.assert_array_equal(q[g.angles][:, g.angles], np.eye(int(g.angles.sum())))
    assert np.abs(g.rot - np.eye(2)).max() > 1e-3  # the frame has turned
    np.testing.assert_allclose(q @ g.q_block(np.arange(g.n_vars), inverse=True), np.eye(g.state_dim), atol=1e-14)


def test_information_is_the_inverse_of_the_covariance(rng):
    g = _joined_3d(rng)
    info = g.to_local_map().info_dense()
    np.testing.assert_allclose(info @ g.cov, np.eye(g.state_dim), atol=1e-8)
    np.testing.assert_array_equal(info, info.T)


def test_covariance_or_information_not_positive_definite_is_refused(rng):
    g = _joined_3d(rng)
    bad = np.array(g.cov_tilde, order="F")
    bad[3, 3] = -1.0
    with pytest.raises(SolverError, match="covariance of the global map is not positive definite"):
        g.replace(cov_tilde=bad).to_local_map()
    m = noisy_local_maps(make_world(2, 6, 6, rng), rng, 2)[0]
    info = m.info_dense().copy()
    info[0, 0] = -info[0, 0]
    with pytest.raises(SolverError, match="information of map 'noisy_1' is not positive definite"):
        CovarianceMap.from_local_map(m.replace(info=info))


@pytest.mark.parametrize("n", [0, 1, MIRROR_BLOCK - 1, MIRROR_BLOCK, 2 * MIRROR_BLOCK + 5])
def test_mirror_lower_copies_the_lower_triangle_up_in_place(n, rng):
    for order in ("F", "C"):
        matrix = np.array(rng.normal(size=(n, n)), order=order)
        lower = np.tril(matrix)
        out = _mirror_lower(matrix)
        assert out is matrix
        np.testing.assert_array_equal(out, lower + np.tril(lower, -1).T)


def test_symmetric_columns_of_the_stored_lower_triangle(rng):
    full = rng.normal(size=(9, 9))
    full = full + full.T
    lower = np.tril(full) + np.triu(rng.normal(size=(9, 9)), 1)  # what lies above the diagonal is never read
    cols = np.array([0, 4, 8, 5])
    np.testing.assert_array_equal(_sym_columns(lower, cols), full[:, cols])


def test_a_submap_that_cannot_be_fused_is_refused_with_the_reason(rng, monkeypatch):
    import linear_slam_ros.joining.sequential as sequential

    maps = noisy_local_maps(make_world(2, 12, 30, rng, loops=1.2), rng, 2)
    state = sequential_step(SequentialState(), maps[0])
    for submap in maps[1:]:  # the first submap with both new variables and variables the map holds
        lookup = state.global_map.key_set
        is_new = np.array([k not in lookup for k in submap.keys.tolist()])
        if is_new.any() and not is_new.all():
            break
        state = sequential_step(state, submap)
    else:
        pytest.fail("no submap of the stream has both new variables and variables the map holds")
    new_scalar = int(submap.scalar_index(np.flatnonzero(is_new))[0])
    info = submap.info_dense()
    bad_new = info.copy()
    bad_new[new_scalar, new_scalar] = -abs(bad_new[new_scalar, new_scalar])
    with pytest.raises(SolverError, match=rf"submap '{submap.name}': information of its new variables is not positive definite"):
        sequential_step(state, submap.replace(info=bad_new))
    # common block changed so the submap's marginal on them is -delta I: (I + M S_cc)^-1 M is then negative definite
    sc = submap.scalar_index(np.flatnonzero(~is_new))
    sn = submap.scalar_index(np.flatnonzero(is_new))
    marginal = info[np.ix_(sc, sc)] - info[np.ix_(sc, sn)] @ np.linalg.solve(info[np.ix_(sn, sn)], info[np.ix_(sn, sc)])
    g = state.global_map
    in_map = g.scalar_index([lookup[k] for k in submap.keys[~is_new].tolist()])
    s_cc = g.cov[np.ix_(in_map, in_map)]
    delta = 0.5 / np.linalg.eigvalsh(s_cc).max()
    bad_common = info.copy()
    bad_common[np.ix_(sc, sc)] -= marginal + delta * np.eye(sc.size)
    with pytest.raises(SolverError, match=rf"submap '{submap.name}': joint information is not positive definite"):
        sequential_step(state, submap.replace(info=bad_common))
    real_gesv = sequential._gesv
    monkeypatch.setattr(sequential, "_gesv", lambda a, b: (*real_gesv(a, b)[:3], 2))  # LAPACK: U(2, 2) is zero
    with pytest.raises(SolverError, match=rf"submap '{submap.name}': the joint system of its common variables is singular"):
        sequential_step(state, submap)


def test_a_common_pose_s_heading_is_fused_across_the_wrap():
    """Remark 3 in sequential joining: the global map holds pose 2 at +3.13 rad, the submap at -3.13 (0.023 rad apart
    across +-pi); unwrapped, the fused heading was their mean, about 0 (mutation audit, session 26)."""
    from linear_slam_ros.core.frames import change_frame
    from linear_slam_ros.core.geometry import wrap_angle
    from linear_slam_ros.core.local_map import POSE, LocalMap
    from linear_slam_ros.joining.sequential import SequentialState, sequential_step

    kinds = np.array([POSE, POSE], np.int8)
    a = LocalMap(2, 0, 1, np.array([1, 2]), kinds, np.array([1.0, 0, 0, 1.0, 1.0, 3.13]), np.eye(6) * 100, "a")
    b = LocalMap(2, 1, 3, np.array([2, 3]), kinds, np.array([0.0, 1.0, -3.13, -1.0, 1.0, -3.13]), np.eye(6) * 100, "b")
    joined = sequential_step(sequential_step(SequentialState(), a), b).global_map.to_local_map()
    assert joined.frame_id == 3
    heading = change_frame(joined, 0).pose(2)[2]
    assert abs(wrap_angle(heading - np.pi)) < 0.012  # near pi, between +3.13 and -3.13 + 2 pi


def test_the_global_map_s_frame_and_end_pose_after_each_kind_of_submap():
    """Mutation audit (session 26): the frame a sequential map ends in was pinned for streams only."""
    from linear_slam_ros.core.local_map import POSE, LocalMap
    from linear_slam_ros.joining.sequential import SequentialState, sequential_step

    p2 = np.array([POSE, POSE], np.int8)
    a = LocalMap(2, 0, 2, np.array([1, 2]), p2, np.array([1.0, 0, 0.1, 2.0, 0.2, 0.3]), np.eye(6) * 100, "a")
    first = sequential_step(SequentialState(), a)
    assert (first.global_map.frame_id, first.global_map.end_id) == (2, 2)  # robocentric from the first submap
    only_common = LocalMap(2, 2, 1, np.array([1, 0]), p2, first.global_map.x + 0.01, np.eye(6) * 100, "c")
    assert sequential_step(first, only_common).global_map.frame_id == 1  # its end pose, though nothing is new
    no_end = LocalMap(2, 2, None, np.array([3]), np.array([POSE], np.int8), np.array([1.0, 0, 0]), np.eye(3) * 100, "d")
    after = sequential_step(first, no_end).global_map
    assert (after.frame_id, after.end_id) == (2, 2)  # no end pose: the map stays where it was
    # a submap in the frame of a pose the map lacks (4), holding the map's frame pose (2)
    holds_frame = LocalMap(2, 4, 5, np.array([2, 5]), p2, np.array([-1.0, 0, 0, 1.0, 0, 0]), np.eye(6) * 100, "e")
    joined = sequential_step(first, holds_frame).global_map.to_local_map()
    assert joined.frame_id == 5 and sorted(joined.pose_ids.tolist()) == [0, 1, 2, 4]
