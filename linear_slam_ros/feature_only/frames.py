"""Frames defined by features (App. B): their rotation, exact Jacobians, changes of feature frame.

A frame is defined by ``F_O`` (origin) and ``F_X`` (x axis), and in 3D ``F_Y`` (x-y plane);
:func:`choose_frame_features` picks the longest baseline among candidates.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
import numpy.typing as npt
import scipy.sparse as sp

from linear_slam_ros.core.errors import FrameError
from linear_slam_ros.core.feature_frames import (
    expand_reduced,
    frame_rotation,
    n_frame_features,
    reduce_full,
    rotation_derivatives,
)
from linear_slam_ros.core.solvers import DENSE_MAX
from linear_slam_ros.feature_only.maps import FeatureMap, expansion_matrix

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]

_DEGENERATE = 1e-9
"""Relative length below which frame features count as coincident (or collinear)."""


def reframe_features(dim: int, full: FloatArray, frame_rows: Sequence[int]) -> tuple[FloatArray, sp.csr_matrix]:
    """Express full coordinates in the frame defined by the features at ``frame_rows``.

    Args:
        dim: 2 or 3.
        full: ``(N, d)`` coordinates of every feature.
        frame_rows: rows of ``F_O, F_X[, F_Y]`` in ``full``.

    Returns:
        ``(N, d)`` new coordinates (same row order) and the exact Jacobian ``(N d, N d)``.

    Raises:
        GeometryError: degenerate frame features.
    """
    n = full.shape[0]
    o = int(frame_rows[0])
    origin, x_feat = full[o], full[int(frame_rows[1])]
    y_feat = full[int(frame_rows[2])] if dim == 3 else None
    rot = frame_rotation(dim, origin, x_feat, y_feat)
    diff = full - origin
    new = diff @ rot.T
    derivs = rotation_derivatives(dim, origin, x_feat, y_feat)
    # M[i][:, j] = dR_j (P_i - P_O): (N, d, n_dirs)
    m = np.stack([diff @ d.T for d in derivs], axis=-1)
    rows_idx = np.arange(n)

    # per-row blocks: columns i (R), O (-R - sum M), X (M_v1), Y (M_w)
    rows, cols, vals = [], [], []
    d = dim
    m_v1 = m[:, :, :d]
    m_w = m[:, :, d:] if dim == 3 else None
    col_blocks = [(rows_idx, np.broadcast_to(rot, (n, d, d)))]
    o_block = -np.broadcast_to(rot, (n, d, d)) - m_v1 - (m_w if m_w is not None else 0)
    col_blocks.append((np.full(n, o), o_block))
    col_blocks.append((np.full(n, int(frame_rows[1])), m_v1))
    if m_w is not None:
        col_blocks.append((np.full(n, int(frame_rows[2])), m_w))
    for col_feat, blk in col_blocks:
        r = (rows_idx[:, None, None] * d + np.arange(d)[None, :, None]) + np.zeros((1, 1, d), dtype=np.int64)
        c = (col_feat[:, None, None] * d + np.arange(d)[None, None, :]) + np.zeros((1, d, 1), dtype=np.int64)
        rows.append(r.ravel())
        cols.append(c.ravel())
        vals.append(np.ascontiguousarray(blk).ravel())
    jac = sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(n * d, n * d))
    return new, jac  # duplicates (rows O, X, Y) are summed by the CSR constructor


def _reorder(dim: int, full: FloatArray, ids: IntArray, frame_ids: Sequence[int]) -> tuple[FloatArray, IntArray, IntArray]:
    """Return ``(full, ids, perm)`` reordered so that ``frame_ids`` come first, others keep order."""
    pos = {int(f): i for i, f in enumerate(ids.tolist())}
    missing = [f for f in frame_ids if f not in pos]
    if missing:
        raise FrameError(f"frame feature {missing[0]} is not in the map")
    first = [pos[int(f)] for f in frame_ids]
    rest = [i for i in range(ids.size) if i not in set(first)]
    perm = np.array(first + rest, dtype=np.int64)
    return full[perm], ids[perm], perm


def change_feature_frame(fmap: FeatureMap, new_frame_ids: Sequence[int]) -> FeatureMap:
    """Re-express a feature-only map in the frame defined by other features (App. B).

    Information follows ``I' = G^T I G`` with ``G = d x_old / d x_new`` at the new estimate.

    Raises:
        FrameError: a frame feature is not in the map.
        GeometryError: the new frame features are coincident or collinear.
    """
    new_frame_ids = tuple(int(f) for f in new_frame_ids)
    if new_frame_ids == tuple(fmap.frame_ids):
        return fmap
    d = fmap.dim
    k = n_frame_features(d)
    full_old = fmap.full()
    ids_old = fmap.all_ids
    full_perm, ids_new, perm = _reorder(d, full_old, ids_old, new_frame_ids)
    new_full, _ = reframe_features(d, full_perm, list(range(k)))
    x_new = reduce_full(d, new_full)
    # reverse change, at the new estimate: old coordinates from the new ones
    exact_new = expand_reduced(d, x_new)
    old_rows_in_new = np.argsort(perm)[:k]  # where the old frame features sit in the new order
    _, jac_back = reframe_features(d, exact_new, old_rows_in_new.tolist())
    # reorder the back-transformed rows into the old order, then reduce; columns expand from x_new
    n = ids_old.size
    row_perm = (perm[:, None] * d + np.arange(d)).ravel()  # new-order row r is old feature perm[r]
    inv = np.empty(n * d, dtype=np.int64)
    inv[row_perm] = np.arange(n * d)
    jac_old_order = jac_back[inv]
    g = (expansion_matrix(d, n).T @ jac_old_order @ expansion_matrix(d, n)).tocsr()
    info_old = sp.csr_matrix(fmap.info) if sp.issparse(fmap.info) else np.asarray(fmap.info)
    info: Any = g.T @ info_old @ g  # sparse, or dense when the old information was dense
    is_sparse = sp.issparse(info)  # (kept apart: sp.issparse would narrow ``info`` to a type without .toarray)
    if not is_sparse or info.shape[0] <= DENSE_MAX:
        dense = info.toarray() if is_sparse else np.asarray(info)
        info = 0.5 * (dense + dense.T)
    return FeatureMap(d, new_frame_ids, ids_new[k:], x_new, info, fmap.name)
