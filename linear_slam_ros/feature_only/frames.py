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

from linear_slam_ros.core.errors import FrameError, GeometryError
from linear_slam_ros.core.geometry import drot2, rot2
from linear_slam_ros.core.solvers import DENSE_MAX
from linear_slam_ros.feature_only.maps import FeatureMap, expand_reduced, expansion_matrix, n_frame_features, reduce_full

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]

_DEGENERATE = 1e-9
"""Relative length below which frame features count as coincident (or collinear)."""


def frame_rotation(dim: int, origin: FloatArray, x_feat: FloatArray, y_feat: FloatArray | None = None) -> FloatArray:
    """Return ``R`` of the frame defined by features (eqs. B.2-B.4), checking it is well defined.

    Raises:
        GeometryError: coincident frame features, or (3D) collinear ones.
    """
    v1 = x_feat - origin
    scale = max(1.0, float(np.abs(origin).max()), float(np.abs(x_feat).max()))
    n1 = float(np.linalg.norm(v1))
    if n1 < _DEGENERATE * scale:
        raise GeometryError(f"frame features F_O and F_X coincide (|F_X - F_O| = {n1:.3g} m)")
    if dim == 2:
        return rot2(np.arctan2(v1[1], v1[0]))
    assert y_feat is not None
    w = y_feat - origin
    v3 = np.cross(v1, w)
    n3 = float(np.linalg.norm(v3))
    if n3 < _DEGENERATE * n1 * max(float(np.linalg.norm(w)), _DEGENERATE):
        raise GeometryError(
            f"frame features F_O, F_X, F_Y are collinear or coincident (|(F_X - F_O) x (F_Y - F_O)| = {n3:.3g})"
        )
    v2 = np.cross(v3, v1)
    return np.stack([v1 / n1, v2 / np.linalg.norm(v2), v3 / n3])


def _rotation_derivatives(dim: int, origin: FloatArray, x_feat: FloatArray, y_feat: FloatArray | None) -> list[FloatArray]:
    """Return ``dR/dv1_j`` (and ``dR/dw_j`` in 3D) for each coordinate ``j``: list of (d, d)."""
    v1 = x_feat - origin
    if dim == 2:
        phi = np.arctan2(v1[1], v1[0])
        dphi = np.array([-v1[1], v1[0]]) / (v1 @ v1)
        d_rot = drot2(phi)
        return [d_rot * dphi[0], d_rot * dphi[1]]
    assert y_feat is not None
    w = y_feat - origin
    v3 = np.cross(v1, w)
    v2 = np.cross(v3, v1)
    out = []
    for dv1, dw in [(e, np.zeros(3)) for e in np.eye(3)] + [(np.zeros(3), e) for e in np.eye(3)]:
        dv3 = np.cross(dv1, w) + np.cross(v1, dw)
        dv2 = np.cross(dv3, v1) + np.cross(v3, dv1)
        rows = []
        for v, dv in ((v1, dv1), (v2, dv2), (v3, dv3)):
            nv = np.linalg.norm(v)
            u = v / nv
            rows.append((dv - u * (u @ dv)) / nv)
        out.append(np.stack(rows))
    return out


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
    derivs = _rotation_derivatives(dim, origin, x_feat, y_feat)
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


def choose_frame_features(dim: int, positions: dict[int, FloatArray], candidates: Sequence[int]) -> tuple[int, ...]:
    """Pick well-conditioned frame features among ``candidates``: the farthest pair (2D), then in
    3D the third feature farthest from their line.

    Raises:
        GeometryError: too few candidates, or all of them degenerate.
    """
    cand = [int(c) for c in candidates]
    k = n_frame_features(dim)
    if len(cand) < k:
        raise GeometryError(f"a {dim}D frame needs {k} common features, only {len(cand)} available: {cand}")
    pts = np.array([positions[c] for c in cand])
    dist = np.linalg.norm(pts[:, None, :] - pts[None, :, :], axis=-1)
    i, j = np.unravel_index(int(np.argmax(dist)), dist.shape)
    if dist[i, j] <= 0:
        raise GeometryError(f"common features {cand} all coincide")
    if dim == 2:
        return (cand[i], cand[j])
    axis = (pts[j] - pts[i]) / dist[i, j]
    off = pts - pts[i]
    perp = np.linalg.norm(off - np.outer(off @ axis, axis), axis=1)
    m = int(np.argmax(perp))
    if perp[m] <= 1e-6 * dist[i, j]:
        raise GeometryError(f"common features {cand} are collinear")
    return (cand[i], cand[j], cand[m])
