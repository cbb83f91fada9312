"""Exact sequential joining (Sec. 5.1) in covariance form: O(n^2) per submap, no fill to fight.

The paper's recursion keeps the global map in the robocentric frame of the newest end pose and,
for each submap, (1) solves the linear least squares of the global map and the submap in the
submap's start frame, then (2) changes frame to the submap's end pose. In information form step
(2) couples the old origin with every variable, so the information matrix fills in and the
solve of step (1) grows cubic: the reference program did not finish VicPark6898 in 900 s.

Here the same recursion is carried out on the covariance ``S = I^-1``, exactly:

* step (1) touches only the submap's variables: its new variables are conditioned on the common
  ones (``B = I_nn^-1 I_nc``) and the common ones receive the submap's marginal information
  ``I_cc - I_cn B`` by a rank-``c`` update of ``S``;
* step (2) is ``S' = H S H^T`` with ``H = d reframe / d x``, the inverse of eq. (20)'s ``G``.

Both are algebraically identical to the information form (a test checks it to 1e-8); nothing
is dropped. The information matrix is formed (``S^-1``) only when asked for.
"""

from __future__ import annotations

import dataclasses
import functools
import logging
from dataclasses import dataclass
from typing import ClassVar

import numpy as np
import numpy.typing as npt
import scipy.linalg
import scipy.linalg.blas
import scipy.linalg.lapack

from linear_slam_ros.core.errors import FrameError, GeometryError, InvalidMapError, SolverError
from linear_slam_ros.core.frames import change_frame, frame_layout, reframe, reframe_jacobian
from linear_slam_ros.core.geometry import angle_size, pose_size, wrap_angle
from linear_slam_ros.core.local_map import (
    POSE,
    LocalMap,
    StateLayout,
    VariableLayout,
    pitch_lock_fault,
    pose_key,
    replaced_fields,
    seed_key_lookup,
    to_dense,
    var_offsets,
)
from linear_slam_ros.core.runtime import blas_threads

logger = logging.getLogger(__name__)

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]


_syrk = scipy.linalg.blas.get_blas_funcs("syrk", dtype=np.float64)
_syr2k = scipy.linalg.blas.get_blas_funcs("syr2k", dtype=np.float64)
_potrf = scipy.linalg.lapack.dpotrf
_potri = scipy.linalg.lapack.dpotri
_potrs = scipy.linalg.lapack.dpotrs
_gesv = scipy.linalg.lapack.dgesv


def _spd_inverse_lower(matrix: FloatArray, what: str) -> FloatArray:
    """Return the inverse of a symmetric positive definite matrix, in the lower triangle only.

    One Cholesky factorisation and LAPACK's inverse from it (``potrf``, ``potri``): about
    ``n^3`` flops, against ``7 n^3 / 3`` for solving with the identity. Only the lower triangle
    of ``matrix`` is read. On one BLAS thread whatever the caller's setting: OpenBLAS's threaded
    ``potri`` rounds differently with the number of threads, and a joined map must not depend
    on it (the CLI and the node run this strategy on one thread; a library user's
    :class:`~linear_slam_ros.joiner.joiner.Joiner` may not).

    Args:
        matrix: ``(n, n)`` symmetric (lower triangle used).
        what: names the matrix in the error message.

    Raises:
        SolverError: ``matrix`` is not positive definite.
    """
    if matrix.shape[0] == 0:
        return np.zeros((0, 0), order="F")
    with blas_threads(1):
        factor, info = _potrf(matrix, lower=1, clean=0, overwrite_a=0)
        if info == 0:
            factor, info = _potri(factor, lower=1, overwrite_c=1)
    if info != 0:
        raise SolverError(f"{what} is not positive definite")
    return np.asfortranarray(factor)


def _sym_columns(lower: FloatArray, cols: IntArray) -> FloatArray:
    """Return full columns ``cols`` of a symmetric matrix stored in its lower triangle.

    Entry ``(r, c)`` is ``lower[r, c]`` on and below the diagonal and ``lower[c, r]`` above it:
    the whole columns, then each column's part above the diagonal from its row (``lower[c, :c]``),
    a third of the time of gathering whole rows and choosing entry by entry.
    """
    out = lower[:, cols]
    for j, c in enumerate(cols.tolist()):
        out[:c, j] = lower[c, :c]
    return out


def _rotate_rows(rot: FloatArray, blocks: FloatArray) -> FloatArray:
    """Return ``rot @ blocks[v]`` for every ``v`` of ``blocks`` (``(m, d, k)``), as ``(m, d, k)``.

    Narrow blocks go through one matrix product over all of them (``(d, d) @ (d, m k)``, a
    fifth of ``einsum``'s time); wide ones through ``matmul``'s stacked loop, which avoids the
    two transposing copies that then cost more than the product.
    """
    m, d, k = blocks.shape
    if k >= 64:
        return np.matmul(rot, blocks)
    flat = rot @ blocks.transpose(1, 0, 2).reshape(d, m * k)
    return flat.reshape(d, m, k).transpose(1, 0, 2)


MIRROR_BLOCK = 128
"""Columns per block when a lower triangle is mirrored (a block and its transpose stay in cache)."""


def _mirror_lower(matrix: FloatArray) -> FloatArray:
    """Copy the lower triangle of a square matrix onto its upper one, in place; return it.

    Block by block, so the transposed reads stay in cache: four times faster than
    ``tril + tril.T`` at n = 1,700, and no new matrix.
    """
    n = matrix.shape[0]
    for j in range(0, n, MIRROR_BLOCK):
        end = min(j + MIRROR_BLOCK, n)
        matrix[j:end, end:] = matrix[end:, j:end].T
        block = matrix[j:end, j:end]
        below = np.tril_indices(end - j, -1)
        block.T[below] = block[below]
    return matrix


def _copy_lower(dst: FloatArray, src: FloatArray) -> None:
    """Copy the lower triangle of square ``src`` into the top-left corner of ``dst``, block by block.

    Column blocks of :data:`MIRROR_BLOCK` from their diagonal down: about half the memory
    traffic of copying the whole matrix (the upper triangle is not kept up to date anyway; a
    few entries above the diagonal blocks come along).
    """
    n = src.shape[0]
    for j in range(0, n, MIRROR_BLOCK):
        end = min(j + MIRROR_BLOCK, n)
        dst[j:n, j:end] = src[j:, j:end]


def _symmetrize_lower(lower: FloatArray) -> FloatArray:
    """Return the full symmetric matrix whose lower triangle is stored in ``lower`` (a new matrix)."""
    return _mirror_lower(np.array(lower, order="F"))


@dataclass(frozen=True, eq=False)
class CovarianceMap(VariableLayout):
    """A map held by a factored covariance ``S = Q S~ Q^T``: the state of exact sequential joining.

    ``Q`` is block diagonal: every feature position and pose translation has the same block
    ``rot`` (the rotations accumulated by past changes of frame), every pose orientation has its
    own block ``ang_blocks[j]`` (identity in 2D). Keeping ``Q`` apart turns each change of
    frame into a rank-``2p`` update of ``S~`` instead of a congruence of the whole matrix.

    Attributes:
        dim: 2 or 3.
        frame_id: the pose whose frame the variables are in (the newest end pose).
        end_id: the newest end pose (equal to ``frame_id`` between submaps).
        ids, kinds, x: as in :class:`LocalMap`; ``x`` is in the frame of ``frame_id``.
        cov_tilde: ``(n, n)`` Fortran-ordered ``S~``, lower triangle only (the upper one is
            not kept up to date: symmetric BLAS updates cost half; it holds whatever the memory
            held, and a state file writes it as zeros: :data:`LOWER_TRIANGLE_FIELDS`).
        rot: ``(d, d)`` common block of ``Q`` for positions and translations.
        ang_blocks: ``(m_poses, a, a)`` blocks of ``Q`` for pose orientations, in state order.
        name: label for messages.
        layout: the state layout of ``dim`` and ``kinds`` (built when not given).
    """

    dim: int
    frame_id: int
    end_id: int | None
    ids: IntArray
    kinds: npt.NDArray[np.int8]
    x: FloatArray
    cov_tilde: FloatArray
    rot: FloatArray
    ang_blocks: FloatArray
    name: str = "global"
    layout: StateLayout = dataclasses.field(default=None, repr=False)  # type: ignore[assignment]

    LOWER_TRIANGLE_FIELDS: ClassVar[tuple[str, ...]] = ("cov_tilde",)
    """Fields that hold a symmetric matrix in their lower triangle (a state file zeroes the upper one)."""

    def __post_init__(self) -> None:
        if self.layout is None:
            object.__setattr__(self, "layout", StateLayout(self.dim, self.kinds))

    @classmethod
    def from_local_map(cls, local_map: LocalMap, name: str = "global") -> CovarianceMap:
        """Invert a map's information into covariance form (``Q = I``)."""
        cov = _spd_inverse_lower(np.asfortranarray(to_dense(local_map.info)), f"information of map {local_map.name!r}")
        a = angle_size(local_map.dim)
        n_poses = int(np.count_nonzero(local_map.kinds == POSE))
        return cls(
            local_map.dim, local_map.frame_id, local_map.end_id, local_map.ids, local_map.kinds, local_map.x,
            cov, np.eye(local_map.dim), np.tile(np.eye(a), (n_poses, 1, 1)), name,
        )

    # ---------------------------------------------------------------- Q helpers

    @property
    def _unit_angles(self) -> bool:
        """Whether every block of ``ang_blocks`` is exactly 1: in 2D, where a change of frame
        shifts every angle by the same amount (``d angle' / d angle = 1``)."""
        return self.dim == 2

    def _slot_q(self, slot: int) -> FloatArray:
        """Return ``Q``'s ``(p, p)`` block of pose variable ``slot`` (:meth:`q_block` of one pose)."""
        d = self.dim
        q = np.zeros((pose_size(d), pose_size(d)))
        q[:d, :d] = self.rot
        q[d:, d:] = self.ang_blocks[self._pose_row[slot]]
        return q

    @functools.cached_property
    def _pose_row(self) -> IntArray:
        """Row of ``ang_blocks`` for each variable (-1 for features)."""
        is_pose = self.kinds == POSE
        rows = np.full(self.kinds.shape, -1, dtype=np.int64)
        rows[is_pose] = np.arange(int(is_pose.sum()))
        return rows

    def q_block(self, var_indices: IntArray, inverse: bool = False) -> FloatArray:
        """Return the dense block of ``Q`` (or of ``Q^-1``) over the scalars of ``var_indices`` (in order).

        ``Q`` is block diagonal, so the block of ``Q^-1`` is the inverse of the block of ``Q``:
        ``rot^T`` on positions (``rot`` is a rotation) and each angle block inverted.
        """
        d = self.dim
        sizes = self.sizes[var_indices]
        r = int(sizes.sum())
        q = np.zeros((r, r))
        starts = var_offsets(sizes)
        pos = starts[:, None] + np.arange(d)
        q[pos[:, :, None], pos[:, None, :]] = self.rot.T if inverse else self.rot
        is_pose = self.kinds[var_indices] == POSE
        if is_pose.any():
            ang = starts[is_pose][:, None] + np.arange(d, d + angle_size(d))
            if self._unit_angles:
                q[ang, ang] = 1.0
            else:
                blocks = self.ang_blocks[self._pose_row[var_indices[is_pose]]]
                q[ang[:, :, None], ang[:, None, :]] = np.linalg.inv(blocks) if inverse else blocks
        return q

    def _apply_q(self, mat: FloatArray, inverse: bool = False, transpose: bool = False) -> FloatArray:
        """Return ``Q @ mat``, ``Q^-1 @ mat`` or ``Q^-T @ mat`` for ``mat`` of shape ``(n, k)``.

        ``rot`` is a rotation (``rot^-1 = rot^T``); the angle blocks are inverted as they are.
        """
        out = np.empty_like(mat)
        pos = self.layout.position_index
        rot = self.rot if inverse == transpose else self.rot.T
        out[pos] = _rotate_rows(rot, mat[pos])
        ang = self.layout.angle_index
        if ang.size and self._unit_angles:
            out[ang] = mat[ang]
        elif ang.size:
            blocks = self.ang_blocks
            if inverse:
                blocks = np.linalg.inv(blocks).astype(np.float64, copy=False)
            if transpose:
                blocks = blocks.transpose(0, 2, 1)
            out[ang] = np.einsum("vij,vjk->vik", blocks, mat[ang])
        return out

    @property
    def cov(self) -> FloatArray:
        """``(n, n)`` covariance ``S = Q S~ Q^T`` in the frame of ``frame_id`` (O(n^2) to form)."""
        half = self._apply_q(_symmetrize_lower(self.cov_tilde))  # Q S~
        return _mirror_lower(self._apply_q(half.T))  # Q (Q S~)^T, symmetric

    def to_local_map(self) -> LocalMap:
        """Return the map in information form, dense: ``I = S^-1 = Q^-T S~^-1 Q^-1``.

        ``S~`` is inverted as it is stored (lower triangle, one ``potrf`` and ``potri``), then
        ``Q^-T`` is applied on both sides (O(n^2)); ``S`` itself is never formed.

        Raises:
            SolverError: the covariance is not positive definite.
        """
        inv_tilde = _mirror_lower(_spd_inverse_lower(self.cov_tilde, "covariance of the global map"))
        half = self._apply_q(inv_tilde, inverse=True, transpose=True)  # Q^-T S~^-1
        info = self._apply_q(half.T, inverse=True, transpose=True)  # Q^-T (Q^-T S~^-1)^T, symmetric
        return LocalMap.trusted(
            self.dim, self.frame_id, self.end_id, self.ids, self.kinds, self.x, _mirror_lower(info), self.name,
            self.layout,
        )

    def replace(self, **changes: object) -> CovarianceMap:
        """Return a copy with some fields changed (the layout is shared unless ``dim`` or ``kinds`` change)."""
        return CovarianceMap(**replaced_fields(self, changes))

    def change_frame(self, new_frame_id: int, _in_place: bool = False) -> CovarianceMap:
        """Re-express the map in the frame of its pose ``new_frame_id`` (``S' = H S H^T``, exactly).

        With ``H = D + F E_s^T`` (block diagonal plus the slot's column block) and
        ``Q' = D~ Q`` (``D~`` is ``D`` with the slot block chosen so ``Q'`` keeps one common
        translation block), ``H Q = Q' (I + F~ E_s^T)`` and
        ``S~' = S~ + A M^T + M A^T`` with ``A = F~`` and ``M = S~[:, s] + A S~_ss / 2``.

        ``_in_place`` lets the joiner reuse a matrix it has just created and shares with nobody.

        Raises:
            FrameError: ``new_frame_id`` is not a pose of the map.
            GeometryError: a 3D pose would have pitch +-90 deg in the new frame (its Euler angles are
                singular there).
        """
        if new_frame_id == self.frame_id:
            return self
        slot = self.index_of(pose_key(new_frame_id))
        if slot is None:
            raise FrameError(f"pose {new_frame_id} is not in the global map (frame pose {self.frame_id})")
        d, p = self.dim, pose_size(self.dim)
        layout = frame_layout(d, self.kinds, slot, self.offsets)
        x_new = reframe(d, self.x, layout)
        ids = self.ids.copy()
        ids[slot] = self.frame_id
        if d == 3:  # before anything is changed (_in_place)
            fault = pitch_lock_fault(self.name, new_frame_id, x_new, self.angle_index, ids[self.kinds == POSE])
            if fault is not None:
                raise GeometryError(fault)
        jac = reframe_jacobian(d, self.x, layout)
        pos_idx, ang_idx, cols = layout
        n = self.state_dim
        rot_new = jac.rot @ self.rot
        # Q' angle blocks: ang_self @ Q_ang for every pose but the slot, identity there.
        # (in 2D every block is and stays 1: the same array, shared)
        if not self._unit_angles:
            slot_row = int(self._pose_row[slot])
            others = np.delete(np.arange(self.ang_blocks.shape[0]), slot_row)
            ang_new = self.ang_blocks.copy()
            ang_new[others] = jac.ang_self @ self.ang_blocks[others]
            ang_new[slot_row] = np.eye(p - d)
        else:
            ang_new = self.ang_blocks
        q_ss = self._slot_q(slot)
        q_new_ss_inv = np.eye(p)  # Q'_ss^-1: the slot's new block is (rot_new, identity)
        q_new_ss_inv[:d, :d] = rot_new.T
        # F~ = Q'^-1 (F - E_s Z) Q_ss with Z = Q'_ss Q_ss^-1.
        f_tilde = np.zeros((n, p))
        f_tilde[pos_idx] = _rotate_rows(rot_new.T, jac.pos_frame) @ q_ss
        if ang_idx.size and self._unit_angles:
            f_tilde[ang_idx] = jac.ang_frame @ q_ss
        elif ang_idx.size:
            inv_ang = np.linalg.inv(ang_new[others])
            f_tilde[ang_idx] = inv_ang @ jac.ang_frame @ q_ss
        f_tilde[cols] = q_new_ss_inv @ jac.slot @ q_ss - np.eye(p)
        cov_t = self.cov_tilde if _in_place else np.array(self.cov_tilde, order="F", copy=True)
        col_s = _sym_columns(cov_t, cols)
        m = col_s + 0.5 * f_tilde @ col_s[cols]
        cov_t = _syr2k(1.0, f_tilde, m, beta=1.0, c=cov_t, lower=1, overwrite_c=True)
        moved = self.replace(
            frame_id=new_frame_id, ids=ids, x=x_new, cov_tilde=cov_t, rot=rot_new,
            ang_blocks=ang_new,
        )
        old_key = pose_key(self.frame_id)
        keys = self.keys.copy()
        keys[slot] = old_key
        key_set = dict(self.key_set)
        del key_set[pose_key(new_frame_id)]
        key_set[old_key] = slot
        seed_key_lookup(moved, keys, key_set)  # one key changed: derived, not rebuilt
        return moved


@dataclass(frozen=True)
class SequentialState:
    """State of exact sequential joining: the global map (or ``None``) and the count joined."""

    global_map: CovarianceMap | None = None
    n_joined: int = 0


def _fuse(global_map: CovarianceMap, submap: LocalMap) -> CovarianceMap:
    """Linear LS of a covariance-form global map and a submap in the same frame (eqs. 12-17).

    The submap's new variables are conditioned on its common ones (``B = I_nn^-1 I_nc``); the
    common ones receive its marginal information ``M = I_cc - I_cn B`` by a rank-``c`` update.
    """
    g = global_map
    lookup = g.key_set
    pos = np.fromiter((lookup.get(k, -1) for k in submap.keys.tolist()), np.int64, count=submap.n_vars)
    common_vars = np.flatnonzero(pos >= 0)
    new_vars = np.flatnonzero(pos < 0)
    sc_local = submap.scalar_index(common_vars)
    sc_global = g.scalar_index(pos[common_vars])
    sn_local = submap.scalar_index(new_vars)
    z = submap.x.copy()
    ang = submap.angles[sc_local]
    if ang.any():
        ref = g.x[sc_global[ang]]
        z[sc_local[ang]] = ref + wrap_angle(z[sc_local[ang]] - ref)
    info = to_dense(submap.info)
    i_cc = info[np.ix_(sc_local, sc_local)]
    n_g = g.state_dim
    n_new = sn_local.size
    c = sc_local.size
    if n_new:
        i_nn = info[np.ix_(sn_local, sn_local)]
        i_nc = info[np.ix_(sn_local, sc_local)]
        # LAPACK directly: what cho_factor and cho_solve call, without their wrappers' checks
        # and copies (a step makes some forty small calls; these three cost 0.1 ms less).
        nn_factor, info_code = _potrf(i_nn, lower=1, clean=0, overwrite_a=0)
        if info_code != 0:
            raise SolverError(f"submap {submap.name!r}: information of its new variables is not positive definite")
        gain, _ = _potrs(nn_factor, i_nc, lower=1)  # B = I_nn^-1 I_nc
        cov_nn_cond, _ = _potrs(nn_factor, np.eye(n_new), lower=1)
        marginal = i_cc - i_nc.T @ gain
    else:
        marginal = i_cc

    n_total = n_g + n_new
    cov_t = np.empty((n_total, n_total), order="F")
    _copy_lower(cov_t, g.cov_tilde)
    x = g.x.copy()
    if c:
        q_cc = g.q_block(pos[common_vars])
        cols_c = _sym_columns(g.cov_tilde, sc_global)  # S~[:, c]
        u_tilde = cols_c @ q_cc.T  # Q^-1 S[:, c]
        s_cc = q_cc @ u_tilde[sc_global]  # S[c, c]
        # (I + M S_cc)^-1 M. With M positive semi-definite I + M S_cc is never singular (its
        # eigenvalues, those of I + S_cc^1/2 M S_cc^1/2, are >= 1); gesv would then return M as it is.
        _, _, weight, info_code = _gesv(np.eye(c) + marginal @ s_cc, marginal)
        if info_code != 0:
            raise SolverError(f"submap {submap.name!r}: the joint system of its common variables is singular")
        weight = 0.5 * (weight + weight.T)
        innovation = z[sc_local] - x[sc_global]
        delta = np.zeros((n_g, 1))
        delta[:, 0] = u_tilde @ (weight @ innovation)
        x = x + g._apply_q(delta)[:, 0]
        # S~ -= U~ W U~^T = (U~ L)(U~ L)^T on the whole contiguous array (the factor's new rows
        # are zero, and the new blocks are written below), so BLAS updates it in place.
        w_chol, info_code = _potrf(weight, lower=1, clean=1, overwrite_a=0)
        if info_code != 0:
            raise SolverError(f"submap {submap.name!r}: joint information is not positive definite")
        factor = np.zeros((n_total, c), order="F")
        factor[:n_g] = u_tilde @ w_chol
        cov_t = _syrk(-1.0, factor, beta=1.0, c=cov_t, lower=1, overwrite_c=True)
        s_cc_post = s_cc - s_cc @ weight @ s_cc
    if not n_new:
        same = g.replace(x=x, cov_tilde=cov_t, end_id=submap.end_id if submap.end_id is not None else g.end_id)
        seed_key_lookup(same, g.keys, g.key_set)  # the same variables (nobody mutates a map's lookup)
        return same

    kinds_new = submap.kinds[new_vars]
    n_new_poses = int(np.count_nonzero(kinds_new == POSE))
    a = angle_size(g.dim)
    merged = g.replace(
        end_id=submap.end_id if submap.end_id is not None else g.end_id,
        ids=np.concatenate([g.ids, submap.ids[new_vars]]),
        kinds=np.concatenate([g.kinds, kinds_new]),
        ang_blocks=np.concatenate([g.ang_blocks, np.tile(np.eye(a), (n_new_poses, 1, 1))]),
    )
    new_var_idx = np.arange(g.n_vars, merged.n_vars)
    q_nn_inv = merged.q_block(new_var_idx, inverse=True)
    x_new = z[sn_local]
    if c:
        x_new = x_new - gain @ (x[sc_global] - z[sc_local])
        # S~[n, g] = Q_nn^-1 (-B) Q_cc S~'[c, :]
        cols_c_post = cols_c - factor[:n_g] @ factor[sc_global].T  # S~'[:, c], from the update's factor
        cross = -(q_nn_inv @ gain @ q_cc) @ cols_c_post.T
        cov_t[n_g:, :n_g] = cross
        cov_nn = cov_nn_cond + gain @ s_cc_post @ gain.T
    else:
        cov_t[n_g:, :n_g] = 0.0
        cov_nn = cov_nn_cond
    cov_t[n_g:, n_g:] = q_nn_inv @ cov_nn @ q_nn_inv.T
    out = merged.replace(x=np.concatenate([x, x_new]), cov_tilde=cov_t)
    new_keys = submap.keys[new_vars]
    key_set = dict(lookup)
    key_set.update(zip(new_keys.tolist(), range(g.n_vars, g.n_vars + new_vars.size), strict=True))
    seed_key_lookup(out, np.concatenate([g.keys, new_keys]), key_set)
    return out


def sequential_step(state: SequentialState, submap: LocalMap) -> SequentialState:
    """Join one submap into the global map: a pure function of ``(state, submap)``.

    The submap must be in the frame of a pose the global map holds (normally the global map's
    own frame, the previous end pose), or hold the global map's frame pose. The new global map
    is in the frame of the submap's end pose.

    Raises:
        InvalidMapError: dimension mismatch.
        FrameError: the submap's frame pose is not in the global map; names both ids.
    """
    if state.global_map is None:
        first = CovarianceMap.from_local_map(submap)
        if submap.end_id is not None:
            first = first.change_frame(submap.end_id)
        return SequentialState(first, 1)
    g = state.global_map
    if submap.dim != g.dim:
        raise InvalidMapError(f"submap {submap.name!r} is {submap.dim}D, the global map is {g.dim}D")
    if submap.frame_id != g.frame_id:
        if g.has_pose(submap.frame_id):
            g = g.change_frame(submap.frame_id)
        elif submap.has_pose(g.frame_id):
            submap = change_frame(submap, g.frame_id)
        else:
            raise FrameError(
                f"submap {submap.name!r} is in the frame of pose {submap.frame_id}, which is not in the global map "
                f"(frame pose {g.frame_id})"
            )
    fused = _fuse(g, submap)  # a new matrix, owned by this step
    if fused.end_id is not None and fused.end_id != fused.frame_id:
        fused = fused.change_frame(fused.end_id, _in_place=True)
    return SequentialState(fused, state.n_joined + 1)
