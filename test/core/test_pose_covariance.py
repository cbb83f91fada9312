"""The newest pose's covariance in the map frame equals the whole map's marginal after a change of frame."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp

from linear_slam_ros.core.errors import FrameError, SolverError
from linear_slam_ros.core.frames import change_frame
from linear_slam_ros.core.local_map import pose_key, to_dense
from linear_slam_ros.core.pose_covariance import marginal_covariance, pose_in_frame
from linear_slam_ros.core.solvers import DENSE_MAX
from linear_slam_ros.evaluation.runner import run_join
from linear_slam_ros.evaluation.synthetic import make_world, noisy_local_maps


def _joined(dim: int, rng: np.random.Generator, n_features: int = 20):
    world = make_world(dim, 24, n_features, rng)
    maps = noisy_local_maps(world, rng, steps_per_map=4)
    return run_join(maps, "dc").result, maps[0].frame_id


def _expected(joined, pose_id: int, frame_pose_id: int):
    moved = change_frame(joined, frame_pose_id)
    sc = moved.scalar_index([moved.key_set[pose_key(pose_id)]])
    return moved.x[sc], np.linalg.inv(to_dense(moved.info))[np.ix_(sc, sc)]


@pytest.mark.parametrize("dim", [2, 3])
def test_end_pose_in_the_first_pose_frame_equals_the_moved_maps_marginal(dim, rng):
    joined, first = _joined(dim, rng)
    assert joined.frame_id == joined.end_id != first  # robocentric: the first pose is a variable
    pose, cov = _expected(joined, joined.end_id, first)
    est = pose_in_frame(joined, joined.end_id, first)
    np.testing.assert_allclose(est.pose, pose, atol=1e-12)
    np.testing.assert_allclose(est.cov, cov, rtol=1e-6, atol=1e-12 * np.abs(cov).max())
    assert est.dim == dim and est.pose_id == joined.end_id and est.frame_id == first
    # from a map in a third pose's frame both poses are variables: the same result
    other = int(joined.pose_ids[len(joined.pose_ids) // 2])
    other = other if other != first else int(joined.pose_ids[0])
    est3 = pose_in_frame(change_frame(joined, other), joined.end_id, first)
    np.testing.assert_allclose(est3.pose, pose, atol=1e-9)
    np.testing.assert_allclose(est3.cov, cov, rtol=1e-5, atol=1e-9 * np.abs(cov).max())
    # without the covariance: the same pose, no solve
    assert np.isnan(pose_in_frame(joined, joined.end_id, first, covariance=False).cov).all()


def test_marginal_covariance_dense_and_sparse_paths_agree(rng):
    joined, _ = _joined(2, rng, n_features=60)
    assert joined.state_dim > DENSE_MAX and sp.issparse(joined.info)
    sc = np.array([7, 2, 3], dtype=np.int64)
    full = np.linalg.inv(to_dense(joined.info))
    np.testing.assert_allclose(marginal_covariance(joined, sc), full[np.ix_(sc, sc)], rtol=1e-9)
    dense = joined.replace(info=to_dense(joined.info))
    np.testing.assert_allclose(marginal_covariance(dense, sc), full[np.ix_(sc, sc)], rtol=1e-9)


def test_a_pose_in_its_own_frame_is_exact_and_errors_name_the_problem(rng):
    joined, first = _joined(2, rng)
    own = pose_in_frame(joined, first, first)
    assert not own.pose.any() and not own.cov.any()
    with pytest.raises(FrameError, match=r"pose 12345 is neither the frame \(\d+\) nor a variable of map"):
        pose_in_frame(joined, 12345, first)
    bad = joined.replace(info=-to_dense(joined.info))
    with pytest.raises(SolverError, match="is not positive definite"):
        marginal_covariance(bad, np.array([0, 1, 2], dtype=np.int64))
