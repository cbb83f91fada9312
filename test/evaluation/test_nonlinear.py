"""Nonlinear LS and consistency: NEES of joined noisy maps within the 95% chi-square bounds."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.stats

from linear_slam_ros.core.errors import FrameError, InvalidMapError
from linear_slam_ros.core.frames import change_frame
from linear_slam_ros.core.local_map import FEATURE, POSE
from linear_slam_ros.evaluation.metrics import nees
from linear_slam_ros.evaluation.nonlinear import gauss_newton, refine
from linear_slam_ros.evaluation.objective import MapObjective, chi2
from linear_slam_ros.evaluation.synthetic import make_world, noisy_local_maps
from linear_slam_ros.joining.divide_conquer import join_divide_and_conquer
from support import join_sequential


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("joiner", [join_divide_and_conquer, join_sequential])
def test_nees_within_95_percent_bounds(dim, joiner):
    """Average NEES over 8 seeded Monte Carlo runs lies inside the two-sided 95% interval."""
    world = make_world(dim, 32, 24, np.random.default_rng(7), loops=1.1)
    values = []
    for run in range(8):
        maps = noisy_local_maps(world, np.random.default_rng(1000 + run), steps_per_map=4)
        result = nees(change_frame(joiner(maps), 0), world.truth())
        values.append(result.nees)
    dof, runs = result.dof, len(values)
    lower = scipy.stats.chi2.ppf(0.025, dof * runs) / runs
    upper = scipy.stats.chi2.ppf(0.975, dof * runs) / runs
    assert lower <= np.mean(values) <= upper, (np.mean(values), dof, lower, upper)


def test_gauss_newton_improves_linear_result_and_stays_consistent():
    world = make_world(2, 40, 30, np.random.default_rng(3), loops=1.2)
    maps = noisy_local_maps(world, np.random.default_rng(4), steps_per_map=4)
    linear = join_divide_and_conquer(maps)
    refined = refine(linear, maps)
    assert refined.converged
    assert refined.chi2 <= chi2(linear, maps) + 1e-9
    assert refined.chi2_history[0] == pytest.approx(chi2(linear, maps), rel=1e-9)
    assert nees(refined.map, world.truth(), kinds=(FEATURE,)).consistent


def test_objective_rejects_unknown_variables():
    world = make_world(2, 8, 6, np.random.default_rng(5))
    maps = noisy_local_maps(world, np.random.default_rng(6), steps_per_map=2)
    part = join_divide_and_conquer(maps[:2])
    with pytest.raises(FrameError, match="variable 6 of map 'noisy_3' is not in map 'global'"):
        MapObjective.build(change_frame(part, 0), maps)
    with pytest.raises(FrameError, match="is not in map"):
        gauss_newton(change_frame(part, 0), maps[:3])


def test_nees_needs_truth_for_every_variable():
    world = make_world(2, 8, 6, np.random.default_rng(5))
    maps = noisy_local_maps(world, np.random.default_rng(6), steps_per_map=2)
    joined = change_frame(join_divide_and_conquer(maps), 0)
    truth = world.truth()
    truth.pop((POSE, 4))
    with pytest.raises(InvalidMapError, match="no ground truth for pose 4"):
        nees(joined, truth)


@pytest.mark.parametrize("dim", [2, 3])
def test_the_jacobian_s_kept_pattern_gives_scipy_s_conversion_at_every_state(dim):
    """The Jacobian's CSR pattern is worked out once per objective; later states only permute values into it."""
    import scipy.sparse as sp

    from linear_slam_ros.evaluation.objective import _block_triplets

    world = make_world(dim, 16, 20, np.random.default_rng(11))
    maps = noisy_local_maps(world, np.random.default_rng(12), steps_per_map=4)
    joined = join_divide_and_conquer(maps)
    objective = MapObjective.build(joined, maps)
    rng = np.random.default_rng(13)
    for k in range(3):  # the first call works the pattern out, the others reuse it
        x = joined.x + (0.0 if k == 0 else 0.05) * rng.standard_normal(joined.x.size)
        _, jac = objective.residuals(x, jacobian=True)
        parts: list = []
        original = objective._jacobian

        def spy(given, parts=parts, original=original):
            parts.extend(given)
            return original(given)

        objective.__dict__["_jacobian"] = spy  # the same blocks, through scipy's triplet conversion
        try:
            objective.residuals(x, jacobian=True)
        finally:
            del objective.__dict__["_jacobian"]
        trip = [_block_triplets(*part) for part in parts]
        reference = sp.csr_matrix(
            (np.concatenate([t[2] for t in trip]), (np.concatenate([t[0] for t in trip]), np.concatenate([t[1] for t in trip]))),
            shape=jac.shape,
        )
        assert jac.has_canonical_format
        np.testing.assert_array_equal(jac.indptr, reference.indptr)
        np.testing.assert_array_equal(jac.indices, reference.indices)
        np.testing.assert_array_equal(jac.data, reference.data)
