"""Symmetric positive-definite solves: dense LAPACK for small systems, sparse Cholesky for large.

Sparse backends, best first (measured on the joined maps' information matrices, README):

1. the system CHOLMOD through ``ctypes`` (:mod:`linear_slam_ros.core.cholmod`): the same library
   and numbers as 2., bit for bit on symmetric matrices (on one that is symmetric only up to
   round-off, the two may read different triangles), but it lets other threads run while it
   factorises (the node's background merges need that);
2. CHOLMOD through ``scikit-sparse``, built against the system SuiteSparse and OpenBLAS
   (``make`` installs Debian's ``libsuitesparse-dev`` and ``libopenblas-dev``);
3. CHOLMOD through the ``cholespy`` wheel, which bundles the reference BLAS: fine on very sparse
   systems, 2x slower on the joined maps' partly dense ones;
4. ``scipy.sparse.linalg.splu`` with a symmetric ordering.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import TYPE_CHECKING, Literal

import numpy as np
import numpy.typing as npt
import scipy.sparse as sp

if TYPE_CHECKING:
    import scipy.sparse.linalg as spla

from linear_slam_ros.core import cholmod
from linear_slam_ros.core.errors import SolverError

try:  # pragma: no cover - exercised through whichever backend is installed
    from sksparse.cholmod import CholmodNotPositiveDefiniteError as _NotPD
    from sksparse.cholmod import cholesky as _cholmod_cholesky
except ImportError:  # pragma: no cover
    _cholmod_cholesky = None
try:  # pragma: no cover
    import cholespy as _cholespy
except ImportError:  # pragma: no cover
    _cholespy = None

logger = logging.getLogger(__name__)


FloatArray = npt.NDArray[np.float64]
SparseBackend = Literal["libcholmod", "sksparse", "cholmod", "scipy"]
Backend = Literal["auto", SparseBackend]

DENSE_MAX = 120
"""Systems up to this size are solved densely (LAPACK beats sparse set-up costs there; tuned on
Manhattan and VicPark6898 between 80 and 250)."""


def backend_name() -> SparseBackend:
    """Return the sparse backend ``auto`` uses."""
    if cholmod.available():
        return "libcholmod"
    if _cholmod_cholesky is not None:
        return "sksparse"
    return "cholmod" if _cholespy is not None else "scipy"


def solve_dense_spd(matrix: FloatArray, rhs: FloatArray) -> FloatArray:
    """Solve ``matrix @ x = rhs`` for a dense SPD ``matrix`` by Cholesky.

    Raises:
        SolverError: the matrix is not positive definite.
    """
    try:
        lower = np.linalg.cholesky(matrix)
    except np.linalg.LinAlgError:
        raise SolverError(f"information matrix of size {matrix.shape[0]} is not positive definite") from None
    y = _solve_lower(lower, rhs, trans=0)
    return _solve_lower(lower, y, trans=1)


def _solve_lower(lower: npt.NDArray[np.floating], rhs: FloatArray, trans: int) -> FloatArray:
    # scipy.linalg is imported on first use: the refiner's process never needs it (0.1 s of its start-up)
    from scipy.linalg.lapack import dtrtrs  # what get_lapack_funcs("trtrs", dtype=np.float64) returns

    x, info = dtrtrs(lower, rhs, lower=1, trans=trans)
    if info != 0:  # pragma: no cover - cannot happen after a successful Cholesky
        raise SolverError(f"triangular solve failed (LAPACK info {info})")
    return x


def solve_sparse_spd(matrix: sp.spmatrix, rhs: FloatArray, backend: Backend = "auto") -> FloatArray:
    """Solve ``matrix @ x = rhs`` for a sparse SPD matrix.

    Args:
        matrix: ``(n, n)`` symmetric positive definite, any scipy sparse format (repeated entries
            are summed, as scipy reads them).
        rhs: ``(n,)`` or ``(n, k)``.
        backend: ``"libcholmod"`` (CHOLMOD through ctypes), ``"sksparse"`` (CHOLMOD through
            scikit-sparse), ``"cholmod"`` (cholespy), ``"scipy"``
            (SuperLU with a symmetric ordering) or ``"auto"`` (the best installed).

    Raises:
        SolverError: the matrix is not positive definite (a pivot not above zero). The condition
            is not estimated: an exactly singular matrix whose pivots round to small positive
            numbers is solved by the CHOLMOD backends into a finite, meaningless answer (scipy's
            refuses it). The joins never pass one: map validation bounds the condition number
            (:mod:`~linear_slam_ros.core.limits`), and a sum of positive definite informations is one.
    """
    rhs = np.ascontiguousarray(rhs, dtype=np.float64)
    if backend == "auto":
        backend = backend_name()
    if backend == "libcholmod":
        return cholmod.solve_spd(matrix, rhs)
    if backend == "sksparse":
        if _cholmod_cholesky is None:
            raise SolverError("backend 'sksparse' requested but scikit-sparse is not installed")
        csc = cholmod.summed_duplicates(matrix if isinstance(matrix, sp.csc_matrix) else sp.csc_matrix(matrix))
        try:
            factor = _cholmod_cholesky(csc)
            # CHOLMOD may pick an LDL^T factorisation, which does not fail on indefinite input
            if np.any(factor.D() <= 0):
                raise _NotPD("non-positive pivot")
        except _NotPD as exc:
            raise SolverError(f"information matrix of size {matrix.shape[0]} is not positive definite: {exc}") from None
        return factor(rhs)
    if backend == "cholmod" and _cholespy is not None:
        # scipy-stubs: the csr_matrix overloads omit the bare sp.spmatrix (a mixin there; what sp.bmat returns)
        csr = cholmod.summed_duplicates(sp.csr_matrix(matrix))  # type: ignore[call-overload]
        try:
            solver = _cholespy.CholeskySolverD(
                csr.shape[0],
                csr.indptr.astype(np.int32),
                csr.indices.astype(np.int32),
                np.ascontiguousarray(csr.data, dtype=np.float64),
                _cholespy.MatrixType.CSR,
            )
        except (RuntimeError, ValueError) as exc:
            raise SolverError(f"sparse Cholesky failed on a {csr.shape[0]}x{csr.shape[0]} system: {exc}") from None
        out = np.empty_like(rhs)
        solver.solve(rhs, out)
        if not np.all(np.isfinite(out)):
            raise SolverError(f"sparse Cholesky produced non-finite values on a {csr.shape[0]}x{csr.shape[0]} system")
        return out
    if backend == "cholmod":
        raise SolverError("backend 'cholmod' requested but cholespy is not installed")
    try:
        lu = symmetric_splu(matrix)
    except SolverError as exc:
        raise SolverError(f"{exc} (size {matrix.shape[0]})") from None
    return np.asarray(lu.solve(rhs), dtype=np.float64)


def symmetric_splu(matrix: FloatArray | sp.spmatrix) -> spla.SuperLU:
    """Return SuperLU's factorisation of a symmetric ``matrix``, refusing one not positive definite.

    A symmetric ordering (``MMD_AT_PLUS_A``) and diagonal pivots only (symmetric mode, pivot
    threshold 0): the factorisation is ``L D L^T`` in disguise, ``U``'s diagonal is ``D``, and the
    matrix is positive definite exactly when every entry of it is positive (with partial pivoting,
    or without this check, an indefinite matrix is factorised and solved without a word).

    Raises:
        SolverError: ``information matrix is singular`` or ``information matrix is not positive
            definite``.
    """
    import scipy.sparse.linalg as spla  # on first use (see _solve_lower)

    csc = cholmod.summed_duplicates(sp.csc_matrix(matrix))  # splu would sum them in the caller's arrays
    try:
        lu = spla.splu(csc, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0, options={"SymmetricMode": True})
    except RuntimeError:
        raise SolverError("information matrix is singular") from None
    if not np.all(lu.U.diagonal() > 0):
        raise SolverError("information matrix is not positive definite")
    return lu


SpdSolve = Callable[[FloatArray], FloatArray]
"""``rhs -> matrix^-1 rhs`` with one factorisation of ``matrix`` kept (see :func:`spd_factor`)."""


def spd_factor(matrix: FloatArray | sp.csr_matrix) -> SpdSolve:
    """Factorise an SPD ``matrix`` once and return its solve, for many right-hand sides given later.

    Dense LAPACK Cholesky up to :data:`DENSE_MAX` scalars (or for a dense matrix); above, CHOLMOD's
    factor kept by the best backend that can keep one (``libcholmod``, ``sksparse``); with the others
    each call solves afresh (:func:`solve_sparse_spd`): the same numbers, without the saving.

    Raises:
        SolverError: the matrix is not positive definite.
    """
    n = int(matrix.shape[0])
    if n <= DENSE_MAX or isinstance(matrix, np.ndarray):
        dense = np.asarray(matrix, dtype=np.float64) if isinstance(matrix, np.ndarray) else matrix.toarray()
        try:
            lower = np.linalg.cholesky(dense)
        except np.linalg.LinAlgError:
            raise SolverError(f"information matrix of size {n} is not positive definite") from None
        return lambda rhs: _solve_lower(lower, _solve_lower(lower, np.asarray(rhs, dtype=np.float64), trans=0), trans=1)
    backend = backend_name()
    if backend == "libcholmod":
        return cholmod.Factor(matrix).solve
    if backend == "sksparse" and _cholmod_cholesky is not None:
        try:
            factor = _cholmod_cholesky(sp.csc_matrix(matrix))
            if np.any(factor.D() <= 0):
                raise _NotPD("non-positive pivot")
        except _NotPD as exc:
            raise SolverError(f"information matrix of size {n} is not positive definite: {exc}") from None
        return lambda rhs: np.asarray(factor(np.ascontiguousarray(rhs, dtype=np.float64)), dtype=np.float64)
    if backend == "cholmod":  # cholespy keeps no factor for later right-hand sides
        kept = sp.csr_matrix(matrix)
        return lambda rhs: solve_sparse_spd(kept, rhs)
    lu = symmetric_splu(matrix)
    return lambda rhs: np.asarray(lu.solve(np.asarray(rhs, dtype=np.float64)), dtype=np.float64)
