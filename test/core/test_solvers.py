"""Sparse and dense SPD solves: every backend agrees; non-SPD systems raise SolverError."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import scipy.sparse as sp

from linear_slam_ros.core import cholmod
from linear_slam_ros.core.errors import SolverError
from linear_slam_ros.core.solvers import backend_name, solve_dense_spd, solve_sparse_spd, symmetric_splu
from support import solve_spd


def _spd(n, rng):
    a = sp.random(n, n, density=0.02, random_state=np.random.RandomState(1)) + sp.eye(n)
    return (a @ a.T + sp.eye(n) * n * 0.01).tocsr()


@pytest.mark.parametrize("backend", ["libcholmod", "sksparse", "cholmod", "scipy"])
def test_backends_agree(backend, rng):
    m = _spd(400, rng)
    b = rng.normal(size=400)
    x = solve_sparse_spd(m, b, backend)
    np.testing.assert_allclose(m @ x, b, atol=1e-9)
    np.testing.assert_allclose(x, solve_dense_spd(m.toarray(), b), atol=1e-9)


def test_auto_prefers_system_cholmod_and_dispatches_dense(rng):
    assert backend_name() == "libcholmod"  # make installs Debian's SuiteSparse
    m = _spd(50, rng)
    b = rng.normal(size=50)
    np.testing.assert_allclose(solve_spd(m.toarray(), b), solve_spd(m, b), atol=1e-10)


def test_not_positive_definite_raises():
    bad = np.diag([1.0, -1.0, 2.0])
    with pytest.raises(SolverError, match="information matrix of size 3 is not positive definite"):
        solve_dense_spd(bad, np.ones(3))
    indefinite = np.array([[1.0, 2.0, 0.0], [2.0, 1.0, 0.0], [0.0, 0.0, 1.0]])  # positive diagonal, eigenvalue -1
    for backend in ("libcholmod", "sksparse", "cholmod", "scipy"):
        for matrix in (bad, indefinite):
            with pytest.raises(SolverError, match="not positive definite"):
                solve_sparse_spd(sp.csr_matrix(matrix), np.ones(3), backend)
    with pytest.raises(SolverError, match="^information matrix is singular$"):
        symmetric_splu(sp.csc_matrix(np.diag([1.0, 0.0, 2.0])))


def test_the_scipy_fallback_factorises_once_and_refuses_what_is_not_positive_definite(rng, monkeypatch):
    import linear_slam_ros.core.solvers as solvers

    monkeypatch.setattr(solvers, "backend_name", lambda: "scipy")  # a machine without any CHOLMOD
    m = _spd(400, rng)  # above DENSE_MAX: the sparse path
    assert m.shape[0] > solvers.DENSE_MAX
    b = rng.normal(size=(400, 3))
    solve = solvers.spd_factor(m)
    np.testing.assert_allclose(solve(b), solve_dense_spd(m.toarray(), b), atol=1e-9)
    shifted = (m - sp.identity(400) * 1e3).tocsr()
    with pytest.raises(SolverError, match="^information matrix is not positive definite$"):
        solvers.spd_factor(shifted)


def test_libcholmod_equals_scikit_sparse_bit_for_bit_and_lets_other_threads_run(rng):
    """The same library and settings: the same numbers; and the interpreter lock is free while it factorises."""
    import threading
    import time

    m = _spd(3000, rng)
    b = rng.normal(size=(3000, 2))
    np.testing.assert_array_equal(solve_sparse_spd(m, b, "libcholmod"), solve_sparse_spd(m, b, "sksparse"))
    np.testing.assert_array_equal(solve_sparse_spd(m, b[:, 0], "libcholmod"), solve_sparse_spd(m, b[:, 0], "sksparse"))
    ticks = []
    done = threading.Event()

    def count() -> None:
        while not done.is_set():
            ticks.append(time.perf_counter())
            time.sleep(0.0005)

    k = 24  # a 3D grid Laplacian: its Cholesky factor fills in, a factorisation of ~0.1 s
    line = sp.diags([-np.ones(k - 1), 2.1 * np.ones(k), -np.ones(k - 1)], [-1, 0, 1])
    eye = sp.identity(k)
    grid = sp.csr_matrix(sp.kron(sp.kron(line, eye), eye) + sp.kron(sp.kron(eye, line), eye) + sp.kron(sp.kron(eye, eye), line))
    counter = threading.Thread(target=count)
    counter.start()
    t0 = time.perf_counter()
    solve_sparse_spd(grid, np.ones(k**3), "libcholmod")
    seconds = time.perf_counter() - t0
    done.set()
    counter.join()
    during = [t for t in ticks if t0 <= t <= t0 + seconds]
    assert seconds > 0.02 and len(during) >= seconds / 0.0005 / 10  # the other thread ran all along


def test_large_factorisations_take_turns_and_small_ones_never_wait(rng, monkeypatch):
    """Two factorisations from ``LARGE_ENTRIES`` stored entries on never run at once (peak memory)."""
    import threading

    from linear_slam_ros.core import cholmod

    monkeypatch.setattr(cholmod, "LARGE_ENTRIES", 1000)
    large, small = _spd(400, rng), _spd(10, rng)
    assert large.nnz >= 1000 > small.nnz
    done = threading.Event()
    result: list[np.ndarray] = []
    worker = threading.Thread(target=lambda: (result.append(cholmod.solve_spd(large, np.ones(400))), done.set()))
    with cholmod.one_large_at_a_time(large.nnz):  # a large factorisation under way
        worker.start()
        assert not done.wait(0.3)  # the other large one waits for it
        np.testing.assert_allclose(small @ cholmod.solve_spd(small, np.ones(10)), np.ones(10), atol=1e-9)  # a small one does not
    assert done.wait(30.0)
    worker.join()
    np.testing.assert_allclose(large @ result[0], np.ones(400), atol=1e-9)
    with cholmod.one_large_at_a_time(small.nnz), cholmod.one_large_at_a_time(small.nnz):  # no lock below the bound
        pass


def test_reused_analysis_solves_as_a_fresh_one_and_analyses_once_per_pattern(rng):
    from linear_slam_ros.core.cholmod import ReusedAnalysis, solve_spd

    def spd(density: float) -> sp.csr_matrix:
        m = rng.standard_normal((80, 80)) * (rng.random((80, 80)) < density)
        return sp.csr_matrix(m @ m.T + 3.0 * np.eye(80))

    a = spd(0.08)
    b = rng.standard_normal(80)
    solver = ReusedAnalysis()
    try:
        for scale in (1.0, 2.0, 0.5):  # same pattern, new values: factorised, not analysed again
            np.testing.assert_allclose(solver.solve(a * scale, b), solve_spd(a * scale, b), rtol=1e-12, atol=1e-14)
        assert (solver.analyses, solver.solves) == (1, 3)
        sub = a.tolil()
        i, j = next((i, j) for i, j in zip(*a.nonzero(), strict=True) if i != j)
        sub[i, j] = sub[j, i] = 0.0
        sub = sp.csr_matrix(sub)
        sub.eliminate_zeros()  # fewer entries: within the analysed pattern
        np.testing.assert_allclose(solver.solve(sub, b), solve_spd(sub, b), rtol=1e-12, atol=1e-14)
        assert solver.analyses == 1
        other = spd(0.2)  # entries outside it: the union is analysed
        np.testing.assert_allclose(solver.solve(other, b), solve_spd(other, b), rtol=1e-12, atol=1e-14)
        assert solver.analyses == 2
        with pytest.raises(SolverError, match="not positive definite"):
            solver.solve(-a, b)
        np.testing.assert_allclose(solver.solve(a, b), solve_spd(a, b), rtol=1e-12, atol=1e-14)  # usable after a failure
    finally:
        solver.close()


def test_a_kept_factor_solves_as_a_fresh_solve_any_number_of_times(rng):
    from linear_slam_ros.core.cholmod import Factor
    from linear_slam_ros.core.solvers import spd_factor

    for m in (_spd(400, rng), _spd(60, rng)):  # CHOLMOD's kept factor; the dense path
        solve = spd_factor(m)
        for _ in range(2):
            b = rng.normal(size=(m.shape[0], 3))
            np.testing.assert_allclose(solve(b), solve_sparse_spd(m, b), atol=1e-10)
        np.testing.assert_allclose(solve(b[:, 0]), solve_sparse_spd(m, b[:, 0]), atol=1e-10)
    with pytest.raises(SolverError, match="information matrix of size 200 is not positive definite"):
        spd_factor(sp.diags(np.r_[np.ones(199), -1.0]).tocsr())
    factor = Factor(_spd(400, rng))
    factor.close()
    with pytest.raises(SolverError, match="CHOLMOD factor used after it was closed"):
        factor.solve(np.ones(400))


def test_cholmod_long_interface_solves_as_the_int_one_and_a_kept_analysis_changes_interface(rng, monkeypatch):
    import linear_slam_ros.core.cholmod as cholmod

    m, b = _spd(300, rng), rng.normal(size=(300, 2))
    small = _spd(60, rng)
    with_int = cholmod.solve_spd(m, b), cholmod.Factor(m).solve(b)
    assert cholmod._api(300, m.nnz).index is np.int32
    monkeypatch.setattr(cholmod, "INT32_MAX_INDEX", small.nnz)  # m goes through cholmod_l_*, small through cholmod_*
    assert cholmod._api(300, m.nnz).index is np.int64 and cholmod._api(60, small.nnz).index is np.int32
    np.testing.assert_array_equal(cholmod.solve_spd(m, b), with_int[0])
    np.testing.assert_array_equal(cholmod.Factor(m).solve(b), with_int[1])
    for limit, index in ((small.nnz, np.int32), (0, np.int64)):  # simplicial LDL': D read through its own index type
        monkeypatch.setattr(cholmod, "INT32_MAX_INDEX", limit)
        assert cholmod._api(3, 3).index is index
        with pytest.raises(SolverError, match="information matrix of size 3 is not positive definite"):
            cholmod.solve_spd(sp.csr_matrix(np.diag([1.0, -1.0, 2.0])), np.ones(3))
    monkeypatch.setattr(cholmod, "INT32_MAX_INDEX", small.nnz)
    solver = cholmod.ReusedAnalysis()
    try:
        np.testing.assert_allclose(solver.solve(small, b[:60, 0]), solve_spd(small, b[:60, 0]), rtol=1e-12)
        assert solver._api is not None and solver._api.index is np.int32
        np.testing.assert_allclose(solver.solve(m, b), solve_spd(m, b), rtol=1e-12)  # a new workspace, for cholmod_l_*
        assert solver._api.index is np.int64 and solver.analyses == 2
        np.testing.assert_allclose(solver.solve(2.0 * m, b), solve_spd(2.0 * m, b), rtol=1e-12)
        assert solver.analyses == 2
    finally:
        solver.close()


def test_cholmod_reads_a_csr_matrix_as_its_transpose_without_touching_it(rng):
    from linear_slam_ros.core import cholmod

    m = _spd(200, rng)
    m.sort_indices()  # the joins' canonical form
    b = rng.normal(size=200)
    api, n, indptr, indices, _ = cholmod._native_csc(m)
    assert np.shares_memory(indptr, m.indptr) and np.shares_memory(indices, m.indices)  # read as CSC, not copied
    shuffled = m.copy()
    for row in range(shuffled.shape[0]):  # the same matrix, its rows' entries out of order
        lo, hi = shuffled.indptr[row], shuffled.indptr[row + 1]
        shuffled.indices[lo:hi] = shuffled.indices[lo:hi][::-1].copy()
        shuffled.data[lo:hi] = shuffled.data[lo:hi][::-1].copy()
    shuffled.has_sorted_indices = False
    before = shuffled.indices.copy()
    np.testing.assert_allclose(cholmod.solve_spd(shuffled, b), cholmod.solve_spd(m.tocsc(), b), rtol=1e-12)
    np.testing.assert_array_equal(shuffled.indices, before)  # the caller's arrays are not sorted in place


def test_cholmod_refuses_a_matrix_that_is_not_square_or_a_right_hand_side_of_another_size(rng):
    from linear_slam_ros.core import cholmod

    m = _spd(50, rng)
    with pytest.raises(SolverError, match=r"matrix is square, got shape \(50, 49\)"):
        cholmod.solve_spd(m[:, :49], np.ones(50))
    with pytest.raises(SolverError, match=r"right-hand side of shape \(3,\) for a 50x50 system"):
        cholmod.solve_spd(m, np.ones(3))
    with pytest.raises(SolverError, match=r"right-hand side of shape \(49, 2\) for a 50x50 system"):
        cholmod.Factor(m).solve(np.ones((49, 2)))
    solver = cholmod.ReusedAnalysis()
    try:
        with pytest.raises(SolverError, match=r"right-hand side of shape \(51,\) for a 50x50 system"):
            solver.solve(m, np.ones(51))
    finally:
        solver.close()


def test_an_int_analysis_that_fails_is_retried_through_the_long_interface(rng, monkeypatch):
    import ctypes
    import dataclasses

    from linear_slam_ros.core import cholmod

    m, b = _spd(300, rng), rng.normal(size=300)
    expected = cholmod.solve_spd(m, b)
    lib, int_api, long_api = cholmod._LOADED
    refusing = dataclasses.replace(int_api, analyze=lambda *_: ctypes.POINTER(cholmod._Factor)())  # NULL: "too large"
    monkeypatch.setattr(cholmod, "_LOADED", (lib, refusing, long_api))
    np.testing.assert_array_equal(cholmod.solve_spd(m, b), expected)
    factor = cholmod.Factor(m)
    assert factor._api is long_api
    np.testing.assert_array_equal(factor.solve(b), expected)
    solver = cholmod.ReusedAnalysis()
    try:
        np.testing.assert_array_equal(solver.solve(m, b), expected)
        assert solver._api is long_api and solver.analyses == 1
    finally:
        solver.close()
    monkeypatch.setattr(cholmod, "_LOADED", (lib, refusing, dataclasses.replace(long_api, analyze=refusing.analyze)))
    with pytest.raises(SolverError, match="CHOLMOD could not analyse a 300x300 system"):
        cholmod.solve_spd(m, b)
    with pytest.raises(SolverError, match="CHOLMOD could not analyse a 300x300 system"):
        cholmod.Factor(m)
    with pytest.raises(SolverError, match="CHOLMOD could not analyse a 300x300 system"):
        cholmod.ReusedAnalysis().solve(m, b)


@pytest.mark.filterwarnings("error::pytest.PytestUnraisableExceptionWarning")
def test_a_factor_without_the_library_says_so_and_is_collected_quietly(monkeypatch):
    import gc

    from linear_slam_ros.core import cholmod

    monkeypatch.setattr(cholmod, "_LIB", None)
    with pytest.raises(SolverError, match=r"CHOLMOD \(libcholmod\) is not installed"):
        cholmod.Factor(sp.eye(3, format="csr"))
    gc.collect()


_OPENMP_PROBE = """
import os
import numpy as np
import scipy.sparse as sp
from linear_slam_ros.core import cholmod
n = 100  # a 100 x 100 grid: supernodes large enough for CHOLMOD's parallel loops
grid = sp.diags([-1.0, 4.0, -1.0], [-1, 0, 1], shape=(n, n))
lap = (sp.kron(sp.identity(n), grid) + sp.kron(sp.diags([-1.0, -1.0], [-1, 1], shape=(n, n)), sp.identity(n))).tocsr()
x = cholmod.solve_spd(lap, np.ones(n * n))
assert np.abs(lap @ x - 1.0).max() < 1e-9
print(os.environ.get("OMP_THREAD_LIMIT", "unset"), len(os.listdir("/proc/self/task")))
"""


def _openmp_probe(limit: str | None) -> list[str]:
    """Run a supernodal factorisation in a fresh process; return its ``OMP_THREAD_LIMIT`` and thread count."""
    env = {k: v for k, v in os.environ.items() if k != "OMP_THREAD_LIMIT"}
    env.update(OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1", PYTHONPATH=str(Path(__file__).resolve().parents[2]))
    if limit is not None:
        env["OMP_THREAD_LIMIT"] = limit
    done = subprocess.run([sys.executable, "-c", _OPENMP_PROBE], env=env, capture_output=True, text=True, timeout=120, check=True)
    return done.stdout.split()


@pytest.mark.skipif(not cholmod.available() or not sys.platform.startswith("linux"), reason="libcholmod, /proc")
def test_cholmod_loads_with_one_openmp_thread_and_leaves_the_environment_as_it_was():
    # the library's loops run on a team of 4 whatever OMP_NUM_THREADS says: a limit the user sets is kept
    assert _openmp_probe("4") == ["4", "4"]
    # without one, the factorisation runs on the calling thread alone, and no limit is left for child processes
    assert _openmp_probe(None) == ["unset", "1"]


@pytest.mark.parametrize("backend", ["libcholmod", "sksparse", "cholmod", "scipy"])
@pytest.mark.parametrize("fmt", ["csc", "csr"])
def test_repeated_entries_are_summed_as_scipy_reads_them(backend, fmt, rng):
    """A matrix with repeated entries is their sum to scipy; CHOLMOD read another matrix (solutions 3 off,
    a review of session 26)."""
    n = 60
    a = sp.random(n, n, density=0.1, random_state=1)
    spd = (a @ a.T + 3.0 * sp.identity(n)).tocsc()
    cols = np.repeat(np.arange(n), np.diff(spd.indptr))
    rows, cols2 = np.concatenate([spd.indices, spd.indices]), np.concatenate([cols, cols])
    order = np.lexsort((rows, cols2))
    halves = np.concatenate([0.5 * spd.data, 0.5 * spd.data])[order]
    indptr = np.concatenate([[0], np.cumsum(np.bincount(cols2, minlength=n))])
    repeated = sp.csc_matrix((halves, rows[order], indptr), shape=(n, n))
    assert not repeated.has_canonical_format and abs(repeated - spd).max() < 1e-15
    given = repeated if fmt == "csc" else repeated.T.tocsr(copy=True)  # CSR of the transpose keeps the repeats
    data_before = given.data.copy()
    x_true = rng.normal(size=n)
    x = solve_sparse_spd(given, spd @ x_true, backend)
    np.testing.assert_allclose(x, x_true, atol=1e-10)
    np.testing.assert_array_equal(given.data, data_before)  # the caller's matrix as it was
