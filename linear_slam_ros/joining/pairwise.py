"""Linear joining of two maps (Sec. 4.3, 6): the step every joining strategy is made of.

Joining two maps that share a frame is a linear least-squares problem (eqs. 12-17): every
variable is observed directly by each map that holds it, so ``A^T I_Z A`` is the scatter-sum of
the two information matrices and ``A^T I_Z Z`` the scatter-sum of ``I z``. The joined estimate is
then moved in closed form to the frame of the newest end pose (eqs. 18-21, :mod:`frames`).
Common poses of pose-only maps have one angle observation wrapped so that the two differ by at
most pi (Remark 3).
"""

from __future__ import annotations

import logging

import numpy as np
import numpy.typing as npt
import scipy.sparse as sp

from linear_slam_ros.core.errors import FrameError, InvalidMapError
from linear_slam_ros.core.frames import change_frame
from linear_slam_ros.core.geometry import wrap_angle
from linear_slam_ros.core.local_map import InfoMatrix, LocalMap, StateLayout, scalar_indices, to_csr, to_dense, var_offsets
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
    if map_a.dim != map_b.dim:
        raise InvalidMapError(f"cannot join a {map_a.dim}D map {map_a.name!r} with a {map_b.dim}D map {map_b.name!r}")
    if map_a.frame_id != map_b.frame_id:
        raise InvalidMapError(
            f"maps {map_a.name!r} and {map_b.name!r} are in frames {map_a.frame_id} and {map_b.frame_id}; align them first"
        )
    lookup = map_a.key_set
    pos = np.fromiter((lookup.get(k, -1) for k in map_b.keys.tolist()), np.int64, count=map_b.n_vars)
    new = pos < 0
    union_of_b = pos.copy()
    union_of_b[new] = map_a.n_vars + np.arange(int(new.sum()))
    ids = np.concatenate([map_a.ids, map_b.ids[new]])
    kinds = np.concatenate([map_a.kinds, map_b.kinds[new]])
    sizes = np.concatenate([map_a.sizes, map_b.sizes[new]])
    offsets = var_offsets(sizes)
    b_to_union = scalar_indices(offsets, sizes, union_of_b)
    n_a = map_a.state_dim
    n = int(sizes.sum())

    z_a = map_a.x
    z_b = map_b.x.copy()
    common_angles = map_b.angles & (b_to_union < n_a) if not new.all() else None
    if common_angles is not None and common_angles.any():
        ref = z_a[b_to_union[common_angles]]
        z_b[common_angles] = ref + wrap_angle(z_b[common_angles] - ref)

    x, joined_info = solve_union(map_a.info, z_a, map_b.info, z_b, b_to_union, n)
    end_id = map_b.end_id if map_b.end_id is not None else map_a.end_id
    layout = StateLayout(map_a.dim, kinds, known_sizes=sizes, known_offsets=offsets)
    return LocalMap.trusted(map_a.dim, map_a.frame_id, end_id, ids, kinds, x, joined_info, name, layout)


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
    scalars ``b_to_union``. Returns the estimate and ``A^T I_Z A`` (dense up to
    :data:`DENSE_MAX` scalars, else CSR). With nothing in common there is nothing to solve.
    """
    n_a = z_a.size
    disjoint = b_to_union.size == 0 or int(b_to_union.min()) >= n_a
    if n <= DENSE_MAX:
        dense_a, dense_b = to_dense(info_a), to_dense(info_b)
        info = np.zeros((n, n))
        info[:n_a, :n_a] = dense_a
        if disjoint:  # the least-squares solution is both estimates side by side
            info[np.ix_(b_to_union, b_to_union)] = dense_b
            x = np.empty(n)
            x[:n_a] = z_a
            x[b_to_union] = z_b
            return x, info
        info[np.ix_(b_to_union, b_to_union)] += dense_b
        rhs = np.zeros(n)
        rhs[:n_a] = dense_a @ z_a
        rhs[b_to_union] += dense_b @ z_b
        return solve_dense_spd(info, rhs), info
    coo_a = to_csr(info_a).tocoo()
    coo_b = to_csr(info_b).tocoo()
    rows = np.concatenate([coo_a.row, b_to_union[coo_b.row]])
    cols = np.concatenate([coo_a.col, b_to_union[coo_b.col]])
    joined = sp.csr_matrix((np.concatenate([coo_a.data, coo_b.data]), (rows, cols)), shape=(n, n))
    rhs = np.zeros(n)
    rhs[:n_a] = coo_a.tocsr() @ z_a
    rhs[b_to_union] += coo_b.tocsr() @ z_b
    return solve_sparse_spd(joined, rhs), joined


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
        return join_in_shared_frame(*align_frames(map_a, map_b), name)
    if map_b.frame_id != seam and not map_b.has_pose(seam):
        raise FrameError(
            f"map {map_b.name!r} (frame pose {map_b.frame_id}) does not hold pose {seam}, the end pose of map "
            f"{map_a.name!r} (frame pose {map_a.frame_id}): the maps share no frame"
        )
    return join_in_shared_frame(change_frame(map_a, seam), change_frame(map_b, seam), name)


def join_pair(map_a: LocalMap, map_b: LocalMap, name: str = GLOBAL_NAME) -> LocalMap:
    """Join ``map_a`` with the later ``map_b`` and move the result to ``map_b``'s end pose.

    This is the Linear SLAM step of Fig. 3: the result is the nonlinear least-squares optimum
    of the two maps' objective (Lemma 1), in the frame of the new end pose.
    """
    return to_end_frame(join_at_seam(map_a, map_b, name))
