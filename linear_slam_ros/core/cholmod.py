"""CHOLMOD through ``ctypes``: the system library's sparse Cholesky, without holding the interpreter lock.

``scikit-sparse`` keeps Python's interpreter lock for the whole factorisation, so a large join
on a background thread stops every other thread of the node for as long (measured: the
arrival thread blocked for the full 0.3 s of a 20,000-pose merge). ``ctypes`` releases the lock
around each foreign call, so here the factorisation runs beside the arrivals. The numbers are
CHOLMOD's with its default settings (the same supernodal/simplicial choice, ordering and
LDL'/LL' factorisation ``scikit-sparse`` asks for), from the same ``libcholmod``.

Only the stable leading fields of CHOLMOD's structs are declared (``cholmod_sparse``,
``cholmod_dense`` and ``cholmod_factor`` have kept their layout since CHOLMOD 1.x);
``cholmod_common`` is an opaque buffer larger than any version's. :func:`available` checks the
library once, on a system with a known solution, before anything relies on it.

Matrices whose entries fit 32-bit indices go through CHOLMOD's ``int`` interface
(``cholmod_*``), larger ones through its ``long`` one (``cholmod_l_*``): scipy's own int32
index arrays are then passed as they are, not copied to int64, and CHOLMOD's ordering and
symbolic arrays are half as large. Measured on the 20,000-pose city graph's final merge
(n = 60,000, 5.6 M stored entries): 110 against 167 MB of peak memory above the matrix,
0.83 against 0.95 s, the same solution bit for bit (CHOLMOD caps supernode merging lower in
the ``int`` interface, so factors of gigabytes could round differently). Its analysis can fail
where the ``long`` one succeeds (the factor's entries must fit too): it is then retried there.

Every entry point reads one triangle of a symmetric matrix, the same way: the upper one of CSC
input, and of a CSR matrix the CSC arrays of its transpose (its lower one), without a copy.

CHOLMOD is loaded with OpenMP limited to one thread (:data:`OPENMP_THREAD_LIMIT`).
"""

from __future__ import annotations

import ctypes
import ctypes.util
import functools
import logging
import os
import threading
from contextlib import AbstractContextManager, nullcontext
from dataclasses import dataclass
from typing import Any, TypeVar

import numpy as np
import numpy.typing as npt
import scipy.sparse as sp

from linear_slam_ros.core.errors import SolverError

logger = logging.getLogger(__name__)

FloatArray = npt.NDArray[np.float64]

_INT, _LONG, _REAL, _DOUBLE, _SYS_A = 0, 2, 1, 0, 0  # CHOLMOD_INT, CHOLMOD_LONG, CHOLMOD_REAL, CHOLMOD_DOUBLE, CHOLMOD_A
INT32_MAX_INDEX = 2**31 - 1
"""Largest dimension or entry count CHOLMOD's ``int`` interface takes; beyond, the ``long`` one."""
_COMMON_BYTES = 1 << 16  # sizeof(cholmod_common) is about 2-3 KB in CHOLMOD 3-5
LARGE_ENTRIES = 1_000_000
"""Stored entries from which :func:`solve_spd` factorises one such matrix at a time in the process.

The node's background merges and its output thread (the stack's merge, the newest pose's exact
covariance) each factorise maps of up to the whole map's size; two at once hold two factors and
workspaces (the final map of garage3d-5000: 132 MB above the matrix for one). On a 2-core machine
whose other core takes the arrivals they share one core anyway, so a large factorisation waits
for the one under way instead of running beside it (docs/scale.md, "The global map sent as serialised
bytes; one large factorisation at a time"). Smaller ones never wait, and neither do :class:`Factor`
(the gate's, on the arrival path, which must not wait for a merge) nor :class:`ReusedAnalysis` (the
refiner's, in a process of its own)."""
_LARGE = threading.Lock()


class _Sparse(ctypes.Structure):
    _fields_ = [
        ("nrow", ctypes.c_size_t), ("ncol", ctypes.c_size_t), ("nzmax", ctypes.c_size_t),
        ("p", ctypes.c_void_p), ("i", ctypes.c_void_p), ("nz", ctypes.c_void_p), ("x", ctypes.c_void_p),
        ("z", ctypes.c_void_p), ("stype", ctypes.c_int), ("itype", ctypes.c_int), ("xtype", ctypes.c_int),
        ("dtype", ctypes.c_int), ("sorted", ctypes.c_int), ("packed", ctypes.c_int),
    ]


class _Dense(ctypes.Structure):
    _fields_ = [
        ("nrow", ctypes.c_size_t), ("ncol", ctypes.c_size_t), ("nzmax", ctypes.c_size_t), ("d", ctypes.c_size_t),
        ("x", ctypes.c_void_p), ("z", ctypes.c_void_p), ("xtype", ctypes.c_int), ("dtype", ctypes.c_int),
    ]


class _Factor(ctypes.Structure):
    _fields_ = [
        ("n", ctypes.c_size_t), ("minor", ctypes.c_size_t), ("Perm", ctypes.c_void_p), ("ColCount", ctypes.c_void_p),
        ("IPerm", ctypes.c_void_p), ("nzmax", ctypes.c_size_t), ("p", ctypes.c_void_p), ("i", ctypes.c_void_p),
        ("x", ctypes.c_void_p), ("z", ctypes.c_void_p), ("nz", ctypes.c_void_p), ("next", ctypes.c_void_p),
        ("prev", ctypes.c_void_p), ("nsuper", ctypes.c_size_t), ("ssize", ctypes.c_size_t), ("xsize", ctypes.c_size_t),
        ("maxcsize", ctypes.c_size_t), ("maxesize", ctypes.c_size_t), ("super", ctypes.c_void_p), ("pi", ctypes.c_void_p),
        ("px", ctypes.c_void_p), ("s", ctypes.c_void_p), ("ordering", ctypes.c_int), ("is_ll", ctypes.c_int),
        ("is_super", ctypes.c_int), ("is_monotonic", ctypes.c_int), ("itype", ctypes.c_int), ("xtype", ctypes.c_int),
        ("dtype", ctypes.c_int),
    ]


@dataclass(frozen=True)
class _Api:
    """One of CHOLMOD's two interfaces: its index type and its functions."""

    itype: int
    index: type[np.integer[Any]]
    start: Any
    finish: Any
    analyze: Any
    factorize: Any
    solve: Any
    free_factor: Any
    free_dense: Any


def _bind(lib: ctypes.CDLL, prefix: str, itype: int, index: type[np.integer[Any]]) -> _Api:
    """Declare the functions ``prefix + name`` of one interface and return them."""
    common = ctypes.c_void_p
    signatures: dict[str, tuple[list[Any], Any]] = {
        "start": ([common], None),
        "finish": ([common], None),
        "analyze": ([ctypes.POINTER(_Sparse), common], ctypes.POINTER(_Factor)),
        "factorize": ([ctypes.POINTER(_Sparse), ctypes.POINTER(_Factor), common], None),
        "solve": ([ctypes.c_int, ctypes.POINTER(_Factor), ctypes.POINTER(_Dense), common], ctypes.POINTER(_Dense)),
        "free_factor": ([ctypes.POINTER(ctypes.POINTER(_Factor)), common], None),
        "free_dense": ([ctypes.POINTER(ctypes.POINTER(_Dense)), common], None),
    }
    functions = {}
    for name, (argtypes, restype) in signatures.items():
        function = getattr(lib, prefix + name)
        function.argtypes = argtypes
        if restype is not None:
            function.restype = restype
        functions[name] = function
    return _Api(itype, index, **functions)


OPENMP_THREAD_LIMIT = "1"
"""``OMP_THREAD_LIMIT`` while CHOLMOD loads, unless the environment sets one (then that one holds).

The system CHOLMOD (SuiteSparse 5, ``libcholmod.so.3``) runs loops of its supernodal factorisation
on a team of 4 OpenMP threads whatever ``OMP_NUM_THREADS`` says (a ``num_threads`` clause fixed when
it was built); only ``OMP_THREAD_LIMIT`` caps the team, and libgomp reads it once, when it loads,
which is when this module loads CHOLMOD. The loops copy and clear, they do not sum: the factor is the
same bit for bit with one thread. On the 2-core target the three extra threads cost more than they
give (docs/scale.md, "One thread for BLAS and for CHOLMOD's OpenMP"): online D&C of sphere2500, offline, 3.8 against 3.2 s
of CPU and 3.6 against 3.2 s of wall time. The variable is set for the load only, so programs this
process starts do not inherit it (the reference program is given the same limit explicitly,
:func:`~linear_slam_ros.evaluation.reference.run_program`). Where libgomp was loaded before (by
another library), the limit does not apply; nothing else changes."""


def _load() -> tuple[ctypes.CDLL, _Api, _Api] | None:
    name = ctypes.util.find_library("cholmod")
    if name is None:
        return None
    limit_set_here = "OMP_THREAD_LIMIT" not in os.environ
    if limit_set_here:
        os.environ["OMP_THREAD_LIMIT"] = OPENMP_THREAD_LIMIT
    try:
        lib = ctypes.CDLL(name)  # loads libgomp, which reads OMP_THREAD_LIMIT now
        return lib, _bind(lib, "cholmod_", _INT, np.int32), _bind(lib, "cholmod_l_", _LONG, np.int64)
    except (OSError, AttributeError):  # pragma: no cover - a broken installation
        return None
    finally:
        if limit_set_here:
            del os.environ["OMP_THREAD_LIMIT"]


_LOADED = _load()
_LIB = None if _LOADED is None else _LOADED[0]


def _api(n: int, nnz: int) -> _Api:
    """The interface for an ``n x n`` matrix of ``nnz`` stored entries: ``int`` when they fit."""
    assert _LOADED is not None
    return _LOADED[1] if max(n, nnz) <= INT32_MAX_INDEX else _LOADED[2]


def _positive_definite(factor: _Factor) -> bool:
    """Whether the factorisation proves the matrix positive definite (LL': it finished; LDL': D > 0)."""
    n = int(factor.n)
    if factor.minor < n:
        return False
    if factor.is_ll or factor.is_super:
        return True
    # simplicial LDL': D(j) is the first entry of column j (the diagonal), at x[p[j]]
    index = ctypes.c_int32 if factor.itype == _INT else ctypes.c_int64
    p = np.ctypeslib.as_array(ctypes.cast(factor.p, ctypes.POINTER(index)), shape=(n + 1,))
    x = np.ctypeslib.as_array(ctypes.cast(factor.x, ctypes.POINTER(ctypes.c_double)), shape=(int(factor.nzmax),))
    return bool(np.all(x[p[:n]] > 0))


IndexArray = npt.NDArray[np.int32] | npt.NDArray[np.int64]


def _sorted_csc(matrix: sp.spmatrix | sp.sparray) -> sp.csc_matrix:
    """Return square symmetric ``matrix`` as CSC with sorted indices, sharing its arrays where it can.

    A CSR matrix's arrays are those of its transpose in CSC, which is the same matrix: they are
    read as such, not converted (a copy of every entry: 68 MB for a 20,000-pose map). Unsorted
    indices are sorted, and repeated entries summed (scipy's convention, which CHOLMOD does not
    follow: it solved another matrix), in a copy: the caller's arrays may be shared with other threads.

    Raises:
        SolverError: the matrix is not square.
    """
    if isinstance(matrix, sp.csr_matrix | sp.csr_array):
        csc, shape = sp.csc_matrix(matrix.transpose()), matrix.shape
    else:
        csc = sp.csc_matrix(matrix)
        shape = csc.shape
    if shape[0] != shape[1]:
        raise SolverError(f"a symmetric positive definite matrix is square, got shape {shape}")
    return summed_duplicates(csc)


SparseT = TypeVar("SparseT", sp.csc_matrix, sp.csr_matrix)


def summed_duplicates(matrix: SparseT) -> SparseT:
    """Return a CSC or CSR matrix with sorted indices and repeated entries summed (what scipy reads it as),
    itself when it is so already, else a copy: solvers that sum in place would change the caller's arrays,
    and CHOLMOD does not sum them at all."""
    if matrix.has_canonical_format:
        return matrix
    out = matrix.copy()
    out.sum_duplicates()
    return out


def _csc_arrays(matrix: sp.spmatrix | sp.sparray) -> tuple[int, npt.NDArray[np.int64], npt.NDArray[np.int64], FloatArray]:
    """Return ``(n, indptr, indices, data)`` of symmetric ``matrix`` as sorted CSC (:func:`_sorted_csc`), indices in 64 bits."""
    csc = _sorted_csc(matrix)
    indptr = np.ascontiguousarray(csc.indptr, dtype=np.int64)
    indices = np.ascontiguousarray(csc.indices, dtype=np.int64)
    return csc.shape[0], indptr, indices, np.ascontiguousarray(csc.data, dtype=np.float64)


def _native_csc(matrix: sp.spmatrix | sp.sparray) -> tuple[_Api, int, IndexArray, IndexArray, FloatArray]:
    """Return the interface for symmetric ``matrix`` and its sorted CSC arrays (:func:`_sorted_csc`), as
    scipy holds them: :func:`_analyze` puts the indices in the interface's type (a copy only if they differ)."""
    csc = _sorted_csc(matrix)
    return _api(csc.shape[0], csc.nnz), csc.shape[0], csc.indptr, csc.indices, np.ascontiguousarray(csc.data, dtype=np.float64)


def _in_type(api: _Api, indptr: IndexArray, indices: IndexArray) -> tuple[IndexArray, IndexArray]:
    """The index arrays in ``api``'s index type (the same arrays when they already are)."""
    return np.ascontiguousarray(indptr, dtype=api.index), np.ascontiguousarray(indices, dtype=api.index)


def _long_api() -> _Api:
    """CHOLMOD's ``long`` interface (where an ``int`` analysis that failed is retried)."""
    assert _LOADED is not None
    return _LOADED[2]


def _check_rhs(rhs: FloatArray, n: int) -> None:
    """Raise :class:`SolverError` unless ``rhs`` has ``n`` rows (CHOLMOD would read past its end)."""
    if rhs.ndim not in (1, 2) or rhs.shape[0] != n:
        raise SolverError(f"right-hand side of shape {rhs.shape} for a {n}x{n} system")


@dataclass(frozen=True)
class _Analysis:
    """An analysed matrix: the interface its workspace was started for, the factor, and CHOLMOD's
    views of the matrix and the right-hand side with the index arrays they point into (kept alive)."""

    api: _Api
    factor: Any
    a_struct: _Sparse
    b_struct: _Dense
    arrays: tuple[IndexArray, IndexArray]


def _analyze(
    api: _Api, common: Any, n: int, indptr: IndexArray, indices: IndexArray, data: FloatArray, b: FloatArray
) -> _Analysis:
    """Start ``common`` for ``api`` and analyse the matrix; an ``int`` analysis that fails is retried
    through the ``long`` interface (the factor's entries must fit in 32 bits too).

    Raises:
        SolverError: neither interface could analyse it (``common`` is finished then).
    """
    for attempt in [api] if api is _long_api() else [api, _long_api()]:
        native = _in_type(attempt, indptr, indices)
        a_struct, b_struct = _structs(attempt, n, *native, data, b)
        attempt.start(common)
        factor = attempt.analyze(ctypes.byref(a_struct), common)
        if factor:
            return _Analysis(attempt, factor, a_struct, b_struct, native)
        attempt.finish(common)
    raise SolverError(f"CHOLMOD could not analyse a {n}x{n} system (out of memory?)")


def _structs(
    api: _Api, n: int, indptr: IndexArray, indices: IndexArray, data: FloatArray, b: FloatArray
) -> tuple[_Sparse, _Dense]:
    """CHOLMOD's views of a symmetric matrix (upper triangle read) and of a Fortran-ordered right-hand side.

    They point into the arrays: the caller keeps them alive while CHOLMOD uses the views.
    ``indptr`` and ``indices`` are of ``api``'s index type.
    """
    ncol = 1 if b.ndim == 1 else b.shape[1]
    a_struct = _Sparse(
        n, n, data.size, indptr.ctypes.data, indices.ctypes.data, None, data.ctypes.data, None,
        1, api.itype, _REAL, _DOUBLE, 1, 1,
    )
    return a_struct, _Dense(n, ncol, n * ncol, n, b.ctypes.data, None, _REAL, _DOUBLE)


def _solve(api: _Api, factor: Any, b_struct: _Dense, b: FloatArray, common: Any) -> FloatArray:
    """Solve with a computed factor; return the solution shaped as ``b`` (CHOLMOD's copy freed).

    Raises:
        SolverError: CHOLMOD could not solve.
    """
    n, ncol = b_struct.nrow, b_struct.ncol
    solution = api.solve(_SYS_A, factor, ctypes.byref(b_struct), common)
    if not solution:
        raise SolverError(f"CHOLMOD could not solve a {n}x{n} system")
    try:
        out_ptr = ctypes.cast(solution.contents.x, ctypes.POINTER(ctypes.c_double))
        x = np.ctypeslib.as_array(out_ptr, shape=(ncol, n)).T.copy()
    finally:
        api.free_dense(ctypes.byref(solution), common)
    return x[:, 0].copy() if b.ndim == 1 else np.ascontiguousarray(x)


def solve_spd(matrix: sp.spmatrix | sp.sparray, rhs: FloatArray) -> FloatArray:
    """Solve ``matrix @ x = rhs`` for a sparse symmetric positive-definite ``matrix`` by CHOLMOD.

    The interpreter lock is released while CHOLMOD analyses, factorises and solves.

    Args:
        matrix: ``(n, n)``, symmetric (both triangles stored; one is read: the upper one of a
            CSR matrix's transpose, i.e. its lower one, and the upper one of any other format).
        rhs: ``(n,)`` or ``(n, k)``.

    Raises:
        SolverError: the library is missing, or the matrix is not positive definite.
    """
    if _LIB is None:
        raise SolverError("CHOLMOD (libcholmod) is not installed")
    api, n, indptr, indices, data = _native_csc(matrix)
    b = np.asfortranarray(rhs, dtype=np.float64)
    _check_rhs(b, n)
    with one_large_at_a_time(indices.size):
        common = ctypes.create_string_buffer(_COMMON_BYTES)
        analysis = _analyze(api, common, n, indptr, indices, data, b)
        api, factor = analysis.api, analysis.factor
        try:
            api.factorize(ctypes.byref(analysis.a_struct), factor, common)
            if not _positive_definite(factor.contents):
                raise SolverError(f"information matrix of size {n} is not positive definite (CHOLMOD)")
            return _solve(api, factor, analysis.b_struct, b, common)
        finally:
            api.free_factor(ctypes.byref(factor), common)
            api.finish(common)


def one_large_at_a_time(entries: int) -> AbstractContextManager[Any]:
    """Return the process's lock for a factorisation of ``entries`` stored entries from :data:`LARGE_ENTRIES` on, else a no-op."""
    return _LARGE if entries >= LARGE_ENTRIES else nullcontext()


class Factor:
    """A CHOLMOD factorisation of one sparse SPD matrix, kept for any number of later solves.

    Not thread-safe; :meth:`close` (or garbage collection) frees CHOLMOD's memory.
    """

    def __init__(self, matrix: sp.spmatrix | sp.sparray) -> None:
        """Analyse and factorise ``matrix`` (symmetric, both triangles stored).

        Raises:
            SolverError: the library is missing, or the matrix is not positive definite.
        """
        self._factor: ctypes._Pointer[_Factor] | None = None
        self._common: ctypes.Array[ctypes.c_char] | None = None  # set once the interface is known (close() reads both)
        if _LIB is None:
            raise SolverError("CHOLMOD (libcholmod) is not installed")
        api, self.n, indptr, indices, data = _native_csc(matrix)
        common = ctypes.create_string_buffer(_COMMON_BYTES)
        analysis = _analyze(api, common, self.n, indptr, indices, data, np.zeros((self.n, 1), order="F"))
        self._api, self._common, self._factor = analysis.api, common, analysis.factor
        factor = analysis.factor
        self._api.factorize(ctypes.byref(analysis.a_struct), factor, self._common)
        if not _positive_definite(factor.contents):
            self.close()
            raise SolverError(f"information matrix of size {self.n} is not positive definite (CHOLMOD)")

    def solve(self, rhs: FloatArray) -> FloatArray:
        """Return ``matrix^-1 rhs`` for ``rhs`` of shape ``(n,)`` or ``(n, k)``.

        Raises:
            SolverError: the factor was closed, or CHOLMOD could not solve.
        """
        if self._factor is None or self._common is None:
            raise SolverError("CHOLMOD factor used after it was closed")
        b = np.asfortranarray(rhs, dtype=np.float64)
        _check_rhs(b, self.n)
        ncol = 1 if b.ndim == 1 else b.shape[1]
        b_struct = _Dense(self.n, ncol, self.n * ncol, self.n, b.ctypes.data, None, _REAL, _DOUBLE)
        return _solve(self._api, self._factor, b_struct, b, self._common)

    def close(self) -> None:
        """Free the factor and CHOLMOD's workspace (idempotent)."""
        if self._factor is not None and self._common is not None:
            self._api.free_factor(ctypes.byref(self._factor), self._common)
        self._factor = None
        if self._common is not None:
            self._api.finish(self._common)
        self._common = None

    def __del__(self) -> None:
        self.close()


def _union_pattern(
    n: int, indptr_a: npt.NDArray[np.int64], indices_a: npt.NDArray[np.int64], indptr_b: npt.NDArray[np.int64],
    indices_b: npt.NDArray[np.int64],
) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.int64]]:
    """The CSC pattern (sorted) holding the entries of two ``n x n`` CSC patterns."""
    cols = np.arange(n, dtype=np.int64)
    keys = np.union1d(
        np.repeat(cols, np.diff(indptr_a)) * n + indices_a, np.repeat(cols, np.diff(indptr_b)) * n + indices_b
    )
    indptr = np.zeros(n + 1, dtype=np.int64)
    np.cumsum(np.bincount(keys // n, minlength=n), out=indptr[1:])
    return indptr, np.ascontiguousarray(keys % n)


class ReusedAnalysis:
    """:func:`solve_spd` for a sequence of matrices that mostly share one sparsity pattern.

    CHOLMOD's analysis (fill-reducing ordering, symbolic factorisation) is done once per pattern
    and kept: a matrix with the pattern of the previous one is only factorised numerically (the
    Gauss-Newton steps of one refinement round). A new pattern is analysed afresh. Not
    thread-safe; :meth:`close` (or garbage collection) frees CHOLMOD's memory.

    Attributes:
        analyses: how many times a pattern was analysed.
        solves: how many systems were solved.
    """

    def __init__(self) -> None:
        self.analyses = 0
        self.solves = 0
        self._common: ctypes.Array[ctypes.c_char] | None = None
        self._api: _Api | None = None  # the interface ``_common`` was started for (and the factor made by)
        self._factor: ctypes._Pointer[_Factor] | None = None
        self._pattern: tuple[npt.NDArray[np.int64], npt.NDArray[np.int64]] | None = None

    def solve(self, matrix: sp.spmatrix | sp.sparray, rhs: FloatArray) -> FloatArray:
        """Solve ``matrix @ x = rhs`` (as :func:`solve_spd`), reusing the analysis of the same pattern.

        Raises:
            SolverError: the library is missing, or the matrix is not positive definite.
        """
        if _LIB is None:
            raise SolverError("CHOLMOD (libcholmod) is not installed")
        n, indptr, indices, data = _csc_arrays(matrix)
        b = np.asfortranarray(rhs, dtype=np.float64)
        _check_rhs(b, n)
        within = self._within_pattern(n, indptr, indices, data)
        if within is None:  # entries the kept pattern lacks: analyse its union with this one (or this one)
            kept = self._pattern
            same_size = kept is not None and kept[0].size == n + 1
            self._pattern = _union_pattern(n, kept[0], kept[1], indptr, indices) if kept is not None and same_size else (
                indptr, indices
            )
            self._free_factor()
            within = self._within_pattern(n, indptr, indices, data)
            assert within is not None
        indptr, indices, data = within  # the kept pattern, this matrix's entries in it (explicit zeros elsewhere)
        if self._factor is None or self._api is None or self._common is None:  # a new pattern: a fresh workspace
            self._finish()
            common = ctypes.create_string_buffer(_COMMON_BYTES)
            analysis = _analyze(_api(n, indices.size), common, n, indptr, indices, data, b)
            self._api, self._common, self._factor = analysis.api, common, analysis.factor
            self.analyses += 1
            native, a_struct, b_struct = analysis.arrays, analysis.a_struct, analysis.b_struct
        else:
            native = _in_type(self._api, indptr, indices)  # kept alive while CHOLMOD reads them
            a_struct, b_struct = _structs(self._api, n, *native, data, b)
        api = self._api
        api.factorize(ctypes.byref(a_struct), self._factor, self._common)
        if not _positive_definite(self._factor.contents):
            self._free_factor()  # a failed factorisation is not reused (the pattern is)
            raise SolverError(f"information matrix of size {n} is not positive definite (CHOLMOD)")
        x = _solve(api, self._factor, b_struct, b, self._common)
        self.solves += 1
        return x

    def _within_pattern(
        self, n: int, indptr: npt.NDArray[np.int64], indices: npt.NDArray[np.int64], data: FloatArray,
    ) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.int64], FloatArray] | None:
        """The kept pattern and ``data`` scattered into it, when the matrix's pattern is a part of it
        (sparse products drop entries that come out exactly zero, so steps differ); else ``None``."""
        if self._pattern is None or self._pattern[0].size != n + 1:
            return None
        old_indptr, old_indices = self._pattern
        if np.array_equal(old_indptr, indptr) and np.array_equal(old_indices, indices):
            return indptr, indices, data
        if indices.size > old_indices.size:
            return None
        old_keys = np.repeat(np.arange(n, dtype=np.int64), np.diff(old_indptr)) * n + old_indices  # sorted
        keys = np.repeat(np.arange(n, dtype=np.int64), np.diff(indptr)) * n + indices
        pos = np.searchsorted(old_keys, keys)
        if pos.size and (pos[-1] >= old_keys.size or not np.array_equal(old_keys[np.minimum(pos, old_keys.size - 1)], keys)):
            return None
        full = np.zeros(old_indices.size)
        full[pos] = data
        return old_indptr, old_indices, full

    def _free_factor(self) -> None:
        if self._factor is not None and self._api is not None and self._common is not None:
            self._api.free_factor(ctypes.byref(self._factor), self._common)
        self._factor = None

    def _finish(self) -> None:
        """Free the factor and CHOLMOD's workspace."""
        self._free_factor()
        if self._common is not None and self._api is not None:
            self._api.finish(self._common)
        self._common = None
        self._api = None

    def expect(self, pattern: sp.spmatrix | sp.sparray) -> None:
        """Take ``pattern``'s structure (symmetric, ``n x n``; its values are ignored) as the one to analyse
        next: the matrices that follow have entries within it (e.g. ``|J|^T |W| |J|`` for ``J^T W J``)."""
        csc = _sorted_csc(pattern)
        self._free_factor()
        self._pattern = (
            np.ascontiguousarray(csc.indptr, dtype=np.int64).copy(), np.ascontiguousarray(csc.indices, dtype=np.int64).copy()
        )

    def close(self) -> None:
        """Free the kept analysis and CHOLMOD's workspace (idempotent)."""
        self._finish()
        self._pattern = None

    def __del__(self) -> None:
        self.close()


@functools.cache
def available() -> bool:
    """Whether CHOLMOD loads and solves a known system correctly (checked once)."""
    if _LIB is None:
        return False
    rng = np.random.default_rng(0)
    m = rng.standard_normal((60, 60)) * (rng.random((60, 60)) < 0.1)
    a = sp.csr_matrix(m @ m.T + np.eye(60) * 2.0)
    x_true = rng.standard_normal(60)
    try:
        ok = bool(np.allclose(solve_spd(a, np.asarray(a @ x_true, dtype=np.float64)), x_true, rtol=1e-10, atol=1e-10))
        not_pd = sp.csr_matrix(np.diag([1.0, -1.0, 2.0]))
        try:
            solve_spd(not_pd, np.ones(3))
            ok = False
        except SolverError:
            pass
    except Exception as exc:  # pragma: no cover - a CHOLMOD whose structs differ: do not use it
        logger.warning("CHOLMOD through ctypes failed its check (%s): using scikit-sparse", exc)
        return False
    return ok
