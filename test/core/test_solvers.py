"""Sparse and dense SPD solves: every backend agrees; non-SPD systems raise SolverError."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp

from linear_slam_ros.core.errors import SolverError
from linear_slam_ros.core.solvers import backend_name, solve_dense_spd, solve_sparse_spd
from support import solve_spd


def _spd(n, rng):
    a = sp.random(n, n, density=0.02, random_state=np.random.RandomState(1)) + sp.eye(n)
    return (a @ a.T + sp.eye(n) * n * 0.01).tocsr()


@pytest.mark.parametrize("backend", ["sksparse", "cholmod", "scipy"])
def test_backends_agree(backend, rng):
    m = _spd(400, rng)
    b = rng.normal(size=400)
    x = solve_sparse_spd(m, b, backend)
    np.testing.assert_allclose(m @ x, b, atol=1e-9)
    np.testing.assert_allclose(x, solve_dense_spd(m.toarray(), b), atol=1e-9)


def test_auto_prefers_system_cholmod_and_dispatches_dense(rng):
    assert backend_name() == "sksparse"  # make installs scikit-sparse on Debian's SuiteSparse
    m = _spd(50, rng)
    b = rng.normal(size=50)
    np.testing.assert_allclose(solve_spd(m.toarray(), b), solve_spd(m, b), atol=1e-10)


def test_not_positive_definite_raises():
    bad = np.diag([1.0, -1.0, 2.0])
    with pytest.raises(SolverError, match="information matrix of size 3 is not positive definite"):
        solve_dense_spd(bad, np.ones(3))
    with pytest.raises(SolverError, match="not positive definite"):
        solve_sparse_spd(sp.csr_matrix(bad), np.ones(3), "sksparse")
