"""Linear joining of two maps (Sec. 4.3, 6): the step every joining strategy is made of.

Joining two maps that share a frame is a linear least-squares problem (eqs. 12-17): every
variable is observed directly by each map that holds it, so ``A^T I_Z A`` is the scatter-sum of
the two information matrices and ``A^T I_Z Z`` the scatter-sum of ``I z``. The joined estimate is
then moved in closed form to the frame of the newest end pose (eqs. 18-21, :mod:`frames`).
Common poses of pose-only maps have one angle observation wrapped so that the two differ by at
most pi (Remark 3).
"""

from __future__ import annotations

import itertools
import logging
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
import scipy.sparse as sp

from linear_slam_ros.core.errors import FrameError, InvalidMapError
from linear_slam_ros.core.frames import change_frame
from linear_slam_ros.core.geometry import wrap_angle
from linear_slam_ros.core.local_map import InfoMatrix, LocalMap, StateLayout, seed_key_lookup, to_dense
from linear_slam_ros.core.solvers import DENSE_MAX, solve_dense_spd, solve_sparse_spd

logger = logging.getLogger(__name__)

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]

GLOBAL_NAME = "global"


def align_frames(map_a: LocalMap, map_b: LocalMap) -> tuple[LocalMap, LocalMap]:
    """Bring two maps into one frame by a closed-form change of frame of one of them.

    ``map_b`` (the later map) moves to ``map_a``'s frame when it holds that pose (divide and
    conquer: the later half holds the earlier half's end pose); otherwise ``map_a`` moves to
    ``map_b``'s frame (the first join of a sequence: map 1 holds map 2's start pose). This order
    matters only when both are possible (pose graphs with forward loop closures); it is the one
    that reproduces the paper's pose-graph figures (Manhattan χ² 214.12).

    Raises:
        FrameError: neither frame pose is in the other map; the message names both ids.
    """
    if map_a.frame_id == map_b.frame_id:
        return map_a, map_b
    if map_b.has_pose(map_a.frame_id):
        return map_a, change_frame(map_b, map_a.frame_id)
    if map_a.has_pose(map_b.frame_id):
        return change_frame(map_a, map_b.frame_id), map_b
    raise FrameError(
        f"map {map_b.name!r} is in the frame of pose {map_b.frame_id}, which is not in map {map_a.name!r} "
        f"(frame pose {map_a.frame_id}), and pose {map_a.frame_id} is not in {map_b.name!r} either: "
        "the maps share no frame"
    )


def join_in_shared_frame(map_a: LocalMap, map_b: LocalMap, name: str = GLOBAL_NAME) -> LocalMap:
    """Solve the linear least squares of eqs. (12)-(17) for two maps in the same frame.

    The result holds ``map_a``'s variables in their order followed by ``map_b``'s new ones, in
    the shared frame, with information ``A^T I_Z A``. Its end pose is ``map_b``'s (the later map).

    Raises:
        InvalidMapError: the maps differ in dimension or frame.
    """
    return union_system(map_a, map_b).solve(name)


@dataclass(frozen=True, eq=False)
class UnionSystem:
    """The least squares of two maps in one frame, set up and not yet solved (eqs. 16-17).

    It holds none of the two maps' information matrices, only their sum: a caller that made the
    maps for this join (a change of frame) lets them go before the factorisation, the largest
    allocation of a join (peak memory, README "Scale").

    Attributes:
        dim: 2 or 3.
        frame_id: the shared frame pose.
        end_id: the joined map's end pose (the later map's, else the earlier's).
        ids: ``(m,)`` variable ids of the union, the earlier map's first.
        kinds: ``(m,)`` their kinds.
        layout: their sizes and offsets in the ``(n,)`` union state.
        keys: ``(m,)`` their keys; ``key_set`` maps each key to its index.
        key_set: key to variable index.
        info: ``(n, n)`` joined information ``A^T I_Z A`` (dense up to :data:`DENSE_MAX`, else canonical CSR).
        rhs: ``(n,)`` ``A^T I_Z (Z - A x)``, the normal equations of the correction to ``x``;
            ``None`` when the maps share nothing (``x`` is then the estimate).
        x: ``(n,)`` the start point: each scalar as the map that first holds it says (the earlier
            map's, then the later map's new ones): both estimates side by side.
    """

    dim: int
    frame_id: int
    end_id: int | None
    ids: IntArray
    kinds: npt.NDArray[np.int8]
    layout: StateLayout
    keys: IntArray
    key_set: dict[int, int]
    info: FloatArray | sp.csr_matrix
    rhs: FloatArray | None
    x: FloatArray

    def solve(self, name: str = GLOBAL_NAME) -> LocalMap:
        """Solve the system: the joined map, in the shared frame.

        Raises:
            SolverError: the joined information is not positive definite.
        """
        x = _estimate(self.info, self.rhs, self.x)
        joined = LocalMap.trusted(self.dim, self.frame_id, self.end_id, self.ids, self.kinds, x, self.info, name, self.layout)
        seed_key_lookup(joined, self.keys, self.key_set)
        return joined


def union_system(map_a: LocalMap, map_b: LocalMap) -> UnionSystem:
    """Set up :func:`join_in_shared_frame`'s least squares for two maps in the same frame, unsolved.

    Raises:
        InvalidMapError: the maps differ in dimension or frame.
    """
    if map_a.dim != map_b.dim:
        raise InvalidMapError(f"cannot join a {map_a.dim}D map {map_a.name!r} with a {map_b.dim}D map {map_b.name!r}")
    if map_a.frame_id != map_b.frame_id:
        raise InvalidMapError(
            f"maps {map_a.name!r} and {map_b.name!r} are in frames {map_a.frame_id} and {map_b.frame_id}; align them first"
        )
    lookup = map_a.key_set
    keys_b = map_b.keys
    pos = np.fromiter(map(lookup.get, keys_b.tolist(), itertools.repeat(-1)), np.int64, count=keys_b.size)
    new = pos < 0
    m_a = map_a.n_vars
    n_new_vars = int(np.count_nonzero(new))
    union_of_b = pos
    union_of_b[new] = np.arange(m_a, m_a + n_new_vars)
    new_sizes = map_b.sizes[new]
    sizes = np.concatenate([map_a.sizes, new_sizes])
    n_a = map_a.state_dim
    offsets = np.empty(sizes.size, dtype=np.int64)
    offsets[:m_a] = map_a.offsets
    new_offsets = offsets[m_a:]
    new_offsets[:1] = n_a
    np.cumsum(new_sizes[:-1], out=new_offsets[1:])
    new_offsets[1:] += n_a
    b_to_union = np.repeat(offsets[union_of_b] - map_b.offsets, map_b.sizes) + np.arange(map_b.state_dim)
    n = n_a + int(new_sizes.sum())

    z_a = map_a.x
    z_b = map_b.x
    if n_new_vars < keys_b.size:
        common_angles = map_b.angles & (b_to_union < n_a)
        if common_angles.any():
            z_b = z_b.copy()
            ref = z_a[b_to_union[common_angles]]
            z_b[common_angles] = ref + wrap_angle(z_b[common_angles] - ref)

    joined_info, rhs, x = _union_normal_equations(map_a.info, z_a, map_b.info, z_b, b_to_union, n)
    end_id = map_b.end_id if map_b.end_id is not None else map_a.end_id
    new_keys = keys_b[new]
    ids = np.concatenate([map_a.ids, map_b.ids[new]])
    kinds = np.concatenate([map_a.kinds, map_b.kinds[new]])
    layout = StateLayout(map_a.dim, kinds, known_sizes=sizes, known_offsets=offsets)
    key_set = dict(lookup)
    key_set.update(zip(new_keys.tolist(), range(m_a, m_a + n_new_vars), strict=True))
    keys = np.concatenate([map_a.keys, new_keys])
    return UnionSystem(map_a.dim, map_a.frame_id, end_id, ids, kinds, layout, keys, key_set, joined_info, rhs, x)


def solve_union(
    info_a: InfoMatrix,
    z_a: FloatArray,
    info_b: InfoMatrix,
    z_b: FloatArray,
    b_to_union: IntArray,
    n: int,
) -> tuple[FloatArray, FloatArray | sp.csr_matrix]:
    """Solve eqs. (16)-(17) for two observations of a union state.

    Map ``a`` observes the first ``len(z_a)`` scalars of the union; map ``b`` observes the
    scalars ``b_to_union`` (distinct). Returns the estimate and ``A^T I_Z A`` (dense up to
    :data:`DENSE_MAX` scalars, else CSR with sorted indices and no duplicates). With nothing in
    common there is nothing to solve.
    """
    info, rhs, x = _union_normal_equations(info_a, z_a, info_b, z_b, b_to_union, n)
    return _estimate(info, rhs, x), info


def _union_normal_equations(
    info_a: InfoMatrix,
    z_a: FloatArray,
    info_b: InfoMatrix,
    z_b: FloatArray,
    b_to_union: IntArray,
    n: int,
) -> tuple[FloatArray | sp.csr_matrix, FloatArray | None, FloatArray]:
    """:func:`solve_union`'s ``A^T I_Z A``, the right-hand side of the correction to the start point and the start
    point (:class:`UnionSystem`); when the maps share nothing, ``None`` and the estimate (both side by side).

    The correction's right-hand side is ``A^T I_Z (Z - A x0)``: only ``b``'s disagreement with ``a`` on
    what they share (``a``'s part is zero), not the coordinates themselves, so round-off does not grow
    with the lever arms of a long chain (an absolute ``A^T I_Z Z`` lost digits in proportion).
    """
    n_a = z_a.size
    disjoint = b_to_union.size == 0 or int(b_to_union.min()) >= n_a
    x0 = np.empty(n)
    x0[b_to_union] = z_b
    x0[:n_a] = z_a  # what both hold: the earlier map's value
    if n <= DENSE_MAX:
        dense_a, dense_b = to_dense(info_a), to_dense(info_b)
        info = np.zeros((n, n))
        info[:n_a, :n_a] = dense_a
        rows, cols = b_to_union[:, None], b_to_union[None, :]
        if disjoint:  # the least-squares solution is both estimates side by side
            info[rows, cols] = dense_b
            return info, None, x0
        info[rows, cols] += dense_b
        rhs = np.zeros(n)
        rhs[b_to_union] = dense_b @ (z_b - x0[b_to_union])
        return info, rhs, x0
    csr_a, csr_b = canonical_csr(info_a), canonical_csr(info_b)
    joined = _padded(csr_a, n) + scatter_csr(csr_b, b_to_union, n)  # both canonical: one merge pass
    if disjoint:
        return joined, None, x0
    rhs = np.zeros(n)
    rhs[b_to_union] = csr_b @ (z_b - x0[b_to_union])
    return joined, rhs, x0


def _estimate(info: FloatArray | sp.csr_matrix, rhs: FloatArray | None, x: FloatArray) -> FloatArray:
    """The joined estimate: ``x`` when the maps share nothing (``rhs`` is ``None``), else ``x`` plus the correction."""
    if rhs is None:
        return x
    return x + _solve_spd(info, rhs)


def _solve_spd(info: FloatArray | sp.csr_matrix, rhs: FloatArray) -> FloatArray:
    """Solve the joined normal equations (dense or canonical CSR information)."""
    if not sp.issparse(info):
        return solve_dense_spd(info, rhs)
    n = info.shape[0]
    # CHOLMOD reads one triangle of a CSC matrix: the CSR arrays read as CSC are the transpose,
    # whose lower triangle is the upper one of the (symmetric) information: no conversion.
    as_csc = sp.csc_matrix((info.data, info.indices, info.indptr), shape=(n, n))
    as_csc.has_sorted_indices = True
    return solve_sparse_spd(as_csc, rhs)


def canonical_csr(matrix: InfoMatrix) -> sp.csr_matrix:
    """Return an information matrix as CSR with sorted indices and no duplicates (a no-op when it is)."""
    if not sp.issparse(matrix):
        return sp.csr_matrix(matrix)
    csr = matrix.tocsr()
    if not csr.has_canonical_format:
        csr = csr.copy()
        csr.sum_duplicates()
    return csr


def _padded(matrix: sp.csr_matrix, n: int) -> sp.csr_matrix:
    """Return ``matrix`` as the leading block of an ``(n, n)`` CSR matrix (shares its arrays)."""
    k = matrix.shape[0]
    indptr = np.empty(n + 1, dtype=matrix.indptr.dtype)
    indptr[: k + 1] = matrix.indptr
    indptr[k + 1 :] = matrix.indptr[-1]
    out = sp.csr_matrix((matrix.data, matrix.indices, indptr), shape=(n, n))
    out.has_sorted_indices = True
    return out


def scatter_csr(matrix: sp.csr_matrix, index: IntArray, n: int) -> sp.csr_matrix:
    """Return ``P^T M P`` as canonical CSR: the ``(k, k)`` matrix ``M`` on the scalars ``index`` of an ``n`` state.

    Args:
        matrix: ``(k, k)`` canonical CSR.
        index: ``(k,)`` distinct target indices.
        n: size of the target state.

    Increasing ``index`` keeps the order within rows: indices are relabelled, rows spread out.
    Otherwise the entries of the transpose are grouped by row (a counting pass) and transposed
    (a second pass, which leaves every row sorted): no per-row sort.
    """
    counts = np.diff(matrix.indptr)
    cols = index[matrix.indices]
    if index.size < 2 or bool(np.all(index[1:] > index[:-1])):
        row_counts = np.zeros(n + 1, dtype=np.int64)
        row_counts[index + 1] = counts
        out = sp.csr_matrix((matrix.data, cols, np.cumsum(row_counts)), shape=(n, n))
        out.has_sorted_indices = True
        return out
    rows = np.repeat(index, counts)
    transposed = sp.coo_matrix((matrix.data, (cols, rows)), shape=(n, n))  # (P^T M P)^T
    transposed.has_canonical_format = True  # no duplicates: tocsr need not sum (nor sort) them
    csc = transposed.tocsr().tocsc()  # sorted CSC arrays of (P^T M P)^T = sorted CSR arrays of P^T M P
    out = sp.csr_matrix((csc.data, csc.indices, csc.indptr), shape=(n, n))
    out.has_sorted_indices = True
    return out


def to_end_frame(local_map: LocalMap) -> LocalMap:
    """Return the map in the robocentric frame of its end pose (unchanged if already there)."""
    if local_map.end_id is None or local_map.end_id == local_map.frame_id:
        return local_map
    return change_frame(local_map, local_map.end_id)


def join_at_seam(map_a: LocalMap, map_b: LocalMap, name: str = GLOBAL_NAME) -> LocalMap:
    """Join ``map_a`` with the later ``map_b`` in one frame by linear LS, without a final transform.

    Maps already in one frame are joined there. Otherwise both move to the *seam*, the end pose
    of ``map_a`` (``map_b`` starts there, so it holds that pose): each change of frame then
    touches one half, never the joined whole, which keeps the information sparser than moving
    the result. The linear step is the same as in :func:`join_pair`; only the frames in which
    later joins linearise differ, and the benchmark figures are unchanged (README).

    Raises:
        FrameError: ``map_b`` neither is in nor holds the seam pose (names both maps and ids).
    """
    if map_a.frame_id == map_b.frame_id:
        return join_in_shared_frame(map_a, map_b, name)
    seam = map_a.end_id
    if seam is None:
        return union_system(*align_frames(map_a, map_b)).solve(name)
    if map_b.frame_id != seam and not map_b.has_pose(seam):
        raise FrameError(
            f"map {map_b.name!r} (frame pose {map_b.frame_id}) does not hold pose {seam}, the end pose of map "
            f"{map_a.name!r} (frame pose {map_a.frame_id}): the maps share no frame"
        )
    # the moved maps are let go once their sum is formed, before the factorisation (peak memory)
    return union_system(change_frame(map_a, seam), change_frame(map_b, seam)).solve(name)


def join_pair(map_a: LocalMap, map_b: LocalMap, name: str = GLOBAL_NAME) -> LocalMap:
    """Join ``map_a`` with the later ``map_b`` and move the result to ``map_b``'s end pose.

    This is the Linear SLAM step of Fig. 3: the result is the nonlinear least-squares optimum
    of the two maps' objective (Lemma 1), in the frame of the new end pose.
    """
    return to_end_frame(join_at_seam(map_a, map_b, name))
