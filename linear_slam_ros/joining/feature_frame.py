"""Pose-feature maps in a frame defined by their features (App. B), for joins without a common pose.

Two maps that share no pose but share point features (at least 2 in 2D, 3 not collinear in 3D)
can still be joined linearly and in closed form: both move to the frame the common features
define (``F_O`` origin, ``F_X`` on the x axis, in 3D ``F_Y`` in the x-y plane), are joined there by
the linear least squares of eqs. (12)-(17), and the result moves to the frame of one of its poses.

A map in the frame of pose ``a`` becomes a :class:`FeatureFramedMap`: the frame features keep
only their free coordinates (1 scalar in 2D, 3 in 3D: :func:`~linear_slam_ros.feature_only.maps.n_reduced`),
every other variable is seen from the feature frame, and pose ``a`` itself becomes a variable (the
state size is unchanged). Both changes are done with the change of frame to a pose of
:mod:`~linear_slam_ros.core.frames`, applied to a *virtual pose* ``V`` at ``F_O`` with the feature
frame's orientation; information follows eq. (20), ``I' = G^T I G`` with ``G`` the exact Jacobian
of the reverse change at the new estimate.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt
import scipy.sparse as sp

from linear_slam_ros.core.errors import FrameError
from linear_slam_ros.core.feature_frames import (
    expand_reduced,
    frame_rotation,
    n_frame_features,
    n_reduced,
    reduce_full,
    rotation_derivatives,
)
from linear_slam_ros.core.frames import frame_layout, reframe, reframe_jacobian
from linear_slam_ros.core.geometry import angles3, dangles3, pose_size
from linear_slam_ros.core.local_map import (
    FEATURE,
    POSE,
    InfoMatrix,
    LocalMap,
    StateLayout,
    scalar_indices,
    var_keys,
    var_offsets,
    var_sizes,
)
from linear_slam_ros.core.solvers import DENSE_MAX
from linear_slam_ros.joining.pairwise import solve_union

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]


@dataclass(frozen=True, eq=False)
class FeatureFramedMap:
    """Poses and features in the frame defined by features ``frame_ids``.

    Attributes:
        dim: 2 or 3.
        frame_ids: ids of ``F_O, F_X`` (2D) or ``F_O, F_X, F_Y`` (3D).
        ids: ``(m,)`` ids of the other variables (the old frame pose among them).
        kinds: ``(m,)`` their kinds.
        x: ``(r + n,)`` state: the frame features' ``r`` free coordinates (m), then each variable,
            in the feature frame (m, rad).
        info: ``(r + n, r + n)`` information of ``x``, dense or CSR.
    """

    dim: int
    frame_ids: tuple[int, ...]
    ids: IntArray
    kinds: npt.NDArray[np.int8]
    x: FloatArray
    info: InfoMatrix

    @property
    def keys(self) -> IntArray:
        """``(m,)`` variable keys (``2 id + kind``) of :attr:`ids`."""
        return var_keys(self.ids, self.kinds)

    @property
    def layout(self) -> StateLayout:
        """Layout of the variables after the reduced frame scalars."""
        return StateLayout(self.dim, self.kinds)


def _virtual_pose(dim: int, frame_xyz: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Return the pose ``V`` of the frame defined by features and ``dV / d(frame features)``.

    Args:
        dim: 2 or 3.
        frame_xyz: ``(k, d)`` coordinates of ``F_O, F_X[, F_Y]``.

    Returns:
        ``(p,)`` ``V`` (translation ``F_O``, orientation of the feature frame) and its ``(p, k d)``
        Jacobian.

    Raises:
        GeometryError: coincident (or, in 3D, collinear) frame features.
    """
    d, k = dim, n_frame_features(dim)
    origin, x_feat = frame_xyz[0], frame_xyz[1]
    y_feat = frame_xyz[2] if dim == 3 else None
    rot = frame_rotation(dim, origin, x_feat, y_feat)
    jac = np.zeros((pose_size(dim), k * d))
    jac[:d, :d] = np.eye(d)
    if dim == 2:
        v1 = x_feat - origin
        angles = np.array([np.arctan2(v1[1], v1[0])])
        dphi = np.array([-v1[1], v1[0]]) / float(v1 @ v1)
        jac[2, 2:4] = dphi
        jac[2, 0:2] = -dphi
    else:
        angles = angles3(rot)
        derivs = np.stack(rotation_derivatives(dim, origin, x_feat, y_feat))  # (6, 3, 3): along v1, then w
        d_ang = dangles3(rot, derivs)  # (3, 6)
        jac[3:, 3:6] = d_ang[:, :3]
        jac[3:, 6:9] = d_ang[:, 3:]
        jac[3:, 0:3] = -(d_ang[:, :3] + d_ang[:, 3:])
    return np.concatenate([origin, angles]), jac


def _selection(rows: IntArray, cols: IntArray, shape: tuple[int, int]) -> sp.csr_matrix:
    return sp.csr_matrix((np.ones(rows.size), (rows, cols)), shape=shape)


def _to_v_frame(dim: int, x_feats_first: FloatArray, kinds: npt.NDArray[np.int8], slot: int) -> tuple[FloatArray, sp.csr_matrix]:
    """Move a state whose frame features come first into their frame; a pose slot receives the old origin.

    Args:
        dim: 2 or 3.
        x_feats_first: ``(n,)`` state of the variables ``kinds`` except ``slot``, frame features first.
        kinds: ``(m,)`` kinds of the variables *with* the slot (a pose), frame features first.
        slot: index in ``kinds`` of the slot.

    Returns:
        The ``(n + p)`` state with frame features first and ``slot`` holding the old origin, all in the
        feature frame, and its ``(n + p, n)`` Jacobian with respect to ``x_feats_first``.
    """
    d, k, p = dim, n_frame_features(dim), pose_size(dim)
    sizes = var_sizes(dim, kinds)
    offsets = var_offsets(sizes)
    n_aug = int(sizes.sum())
    v, dv = _virtual_pose(dim, x_feats_first[: k * d].reshape(k, d))
    slot_cols = int(offsets[slot]) + np.arange(p)
    others = np.setdiff1d(np.arange(n_aug), slot_cols)  # the input's scalars, in order
    x_aug = np.empty(n_aug)
    x_aug[others] = x_feats_first
    x_aug[slot_cols] = v
    layout = frame_layout(dim, kinds, slot, offsets)
    x_new = reframe(dim, x_aug, layout)
    rows = np.concatenate([others, np.repeat(slot_cols, k * d)])
    cols = np.concatenate([np.arange(others.size), np.tile(np.arange(k * d), p)])
    vals = np.concatenate([np.ones(others.size), dv.ravel()])
    aug = sp.csr_matrix((vals, (rows, cols)), shape=(n_aug, others.size))
    jac = reframe_jacobian(dim, x_aug, layout).csr(n_aug) @ aug
    return x_new, jac.tocsr()


def _from_v_frame(dim: int, x_new: FloatArray, kinds: npt.NDArray[np.int8], slot: int) -> tuple[FloatArray, sp.csr_matrix]:
    """Inverse of :func:`_to_v_frame`: back to the frame of the pose in ``slot``, dropping ``V``.

    Returns:
        The ``(n)`` state (frame features first, ``slot`` removed) and its ``(n, n + p)`` Jacobian.
    """
    sizes = var_sizes(dim, kinds)
    offsets = var_offsets(sizes)
    n_aug = int(sizes.sum())
    layout = frame_layout(dim, kinds, slot, offsets)
    x_back = reframe(dim, x_new, layout)
    slot_cols = int(offsets[slot]) + np.arange(pose_size(dim))
    keep = np.setdiff1d(np.arange(n_aug), slot_cols)
    jac = reframe_jacobian(dim, x_new, layout).csr(n_aug)[keep]
    return x_back[keep], jac.tocsr()


def _congruence(info: InfoMatrix, g: sp.csr_matrix) -> InfoMatrix:
    """Return ``G^T I G``, symmetrised; dense up to :data:`DENSE_MAX` scalars, else CSR."""
    product: Any = g.T @ info @ g
    if not isinstance(product, sp.spmatrix | sp.sparray):
        dense = np.asarray(product)
        return 0.5 * (dense + dense.T)
    csr = sp.csr_matrix(product)  # type: ignore[call-overload]  # scipy-stubs omit the base classes (solvers.py)
    if csr.shape[0] <= DENSE_MAX:
        dense = csr.toarray()
        return 0.5 * (dense + dense.T)
    out = (csr + csr.T).tocsr()
    out.data *= 0.5
    out.sum_duplicates()
    out.sort_indices()
    return out


def _feature_indices(local_map: LocalMap, frame_ids: Sequence[int]) -> list[int]:
    out = []
    for f in frame_ids:
        i = local_map.index_of(2 * int(f) + FEATURE)
        if i is None:
            raise FrameError(f"frame feature {f} is not in map {local_map.name!r}")
        out.append(i)
    return out


def to_feature_frame(local_map: LocalMap, frame_ids: Sequence[int]) -> FeatureFramedMap:
    """Re-express a pose-feature map in the frame defined by its features ``frame_ids``.

    Args:
        local_map: the map, in the frame of its pose ``frame_id``.
        frame_ids: ``F_O, F_X`` (2D) or ``F_O, F_X, F_Y`` (3D), features of the map.

    Returns:
        The map in the feature frame; its variables are the map's others in their order, then
        the old frame pose.

    Raises:
        FrameError: a frame feature is not in the map.
        GeometryError: the frame features are coincident (or collinear in 3D).
    """
    dim = local_map.dim
    d, k = dim, n_frame_features(dim)
    fidx = _feature_indices(local_map, frame_ids)
    other = np.setdiff1d(np.arange(local_map.n_vars), fidx)  # sorted: the map's order
    order = np.concatenate([np.array(fidx, dtype=np.int64), other])
    kinds = np.concatenate([local_map.kinds[order], np.array([POSE], dtype=np.int8)])
    old_idx = scalar_indices(local_map.offsets, local_map.sizes, order)  # A-order scalars in the map
    x_v, _ = _to_v_frame(dim, local_map.x[old_idx], kinds, kinds.size - 1)
    y = np.concatenate([reduce_full(dim, x_v[: k * d].reshape(k, d)), x_v[k * d :]])
    # Reverse change (feature frame -> the map's frame) at the new estimate: G = P J_back E.
    n = y.size
    expand = _expansion(dim, n)
    _, back = _from_v_frame(dim, expand @ y, kinds, kinds.size - 1)
    g = _selection(old_idx, np.arange(old_idx.size), (n, n)) @ back @ expand
    info = _congruence(local_map.info, g.tocsr())
    ids = np.concatenate([local_map.ids[other], [local_map.frame_id]]).astype(np.int64)
    return FeatureFramedMap(dim, tuple(int(f) for f in frame_ids), ids, kinds[k:], y, info)


def _expansion(dim: int, n: int) -> sp.csr_matrix:
    """``E`` (``(n + p, n)``): reduced frame scalars to full frame features; the rest unchanged."""
    k, d, r = n_frame_features(dim), dim, n_reduced(dim)
    free = np.flatnonzero(expand_reduced(dim, np.arange(1, r + 1, dtype=float)).ravel() != 0)
    rows = np.concatenate([free, k * d + np.arange(n - r)])
    return _selection(rows, np.arange(n), (k * d + n - r, n))


def from_feature_frame(framed: FeatureFramedMap, pose_id: int, end_id: int | None, name: str) -> LocalMap:
    """Return a feature-framed map in the frame of its pose ``pose_id`` (the frame features as features).

    Args:
        framed: the map in a feature frame.
        pose_id: a pose variable of ``framed``: the new frame.
        end_id: the end pose of the returned map.
        name: its name.

    Returns:
        The map: the frame features first, then the other variables but ``pose_id``, in order.

    Raises:
        FrameError: ``pose_id`` is not a pose of the map.
    """
    dim = framed.dim
    k = n_frame_features(dim)
    slot_var = np.flatnonzero((framed.ids == pose_id) & (framed.kinds == POSE))
    if slot_var.size == 0:
        raise FrameError(f"cannot move a feature-framed map to the frame of pose {pose_id}: not in the map")
    n = framed.x.size
    kinds = np.concatenate([np.full(k, FEATURE, dtype=np.int8), framed.kinds])
    slot = k + int(slot_var[0])
    x_back, _ = _from_v_frame(dim, _expansion(dim, n) @ framed.x, kinds, slot)
    # Reverse change (pose frame -> feature frame) at the new estimate: G = R J_to.
    kinds_back = np.delete(kinds, slot)
    _, to = _to_v_frame(dim, x_back, kinds, slot)
    kept = np.flatnonzero(_expansion(dim, n) @ np.ones(n))  # the rows of x_v that make up y, in y's order
    info = _congruence(framed.info, to[kept])
    ids = np.concatenate([np.array(framed.frame_ids, dtype=np.int64), np.delete(framed.ids, slot_var[0])])
    return LocalMap.trusted(dim, int(pose_id), end_id, ids, kinds_back, x_back, info, name)


def join_feature_framed(map_a: FeatureFramedMap, map_b: FeatureFramedMap) -> FeatureFramedMap:
    """Join two maps in the same feature frame by the linear least squares of eqs. (12)-(17).

    The result holds the frame scalars, ``map_a``'s variables in order, then ``map_b``'s new ones.

    Raises:
        FrameError: the maps are in frames of different features, or of different dimensions.
    """
    if map_a.dim != map_b.dim or map_a.frame_ids != map_b.frame_ids:
        raise FrameError(
            f"cannot join a {map_a.dim}D map in the frame of features {map_a.frame_ids} with a {map_b.dim}D map in "
            f"the frame of features {map_b.frame_ids}"
        )
    r = n_reduced(map_a.dim)
    lookup = {int(key): i for i, key in enumerate(map_a.keys.tolist())}
    pos = np.array([lookup.get(int(key), -1) for key in map_b.keys.tolist()], dtype=np.int64)
    new = pos < 0
    pos[new] = map_a.ids.size + np.arange(int(new.sum()))
    kinds = np.concatenate([map_a.kinds, map_b.kinds[new]])
    sizes = var_sizes(map_a.dim, kinds)
    offsets = r + var_offsets(sizes)
    b_to_union = np.concatenate([np.arange(r), r + scalar_indices(offsets - r, sizes, pos)])
    x, info = solve_union(map_a.info, map_a.x, map_b.info, map_b.x, b_to_union, r + int(sizes.sum()))
    ids = np.concatenate([map_a.ids, map_b.ids[new]])
    return FeatureFramedMap(map_a.dim, map_a.frame_ids, ids, kinds, x, info)
