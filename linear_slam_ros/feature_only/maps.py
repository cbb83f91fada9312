"""Feature-only (D-SLAM) maps: frames defined by features, linear joining (Linear SLAM Sec. 7, App. B).

A feature-only map has no robot pose. Its frame is defined by features: in 2D ``F_O`` (origin)
and ``F_X`` (x axis towards it); in 3D also ``F_Y`` (with ``F_X``, the x-y plane). The frame
features' fixed coordinates leave the state: in 2D ``F_O = (0, 0)`` and ``F_X = (x, 0)`` keep one
scalar; in 3D ``F_O = 0``, ``F_X = (x, 0, 0)``, ``F_Y = (x, y, 0)`` keep three. A change of frame
to other features is ``F' = R (F - F_O)`` with ``R`` built from the new frame features (B.1-B.4).

The state of a :class:`FeatureMap` is ``[reduced frame coordinates, every other feature]``.
Everything about frames works on *full* coordinates ``P`` (``(N, d)``, frame features first) and
converts with :func:`reduce_full` and :func:`expand_reduced`.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from typing import Callable, Sequence

import numpy as np
import numpy.typing as npt
import scipy.sparse as sp

from linear_slam_ros.core.errors import FrameError, GeometryError, InvalidMapError
from linear_slam_ros.core.frames import change_frame
from linear_slam_ros.core.geometry import drot2, rot2
from linear_slam_ros.joining.pairwise import join_pair, solve_union
from linear_slam_ros.core.local_map import FEATURE, POSE, LocalMap, to_dense
from linear_slam_ros.core.solvers import DENSE_MAX

logger = logging.getLogger(__name__)

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]

_DEGENERATE = 1e-9


def n_frame_features(dim: int) -> int:
    """Number of features that define a frame: 2 in 2D, 3 in 3D."""
    return 2 if dim == 2 else 3


def _free_mask(dim: int) -> npt.NDArray[np.bool_]:
    """``(k, d)`` mask of the frame features' coordinates that stay in the state."""
    if dim == 2:
        return np.array([[False, False], [True, False]])
    return np.array([[False, False, False], [True, False, False], [True, True, False]])


def n_reduced(dim: int) -> int:
    """Number of frame-feature scalars kept in the state (1 in 2D, 3 in 3D)."""
    return int(_free_mask(dim).sum())


@dataclass(frozen=True, eq=False)
class FeatureMap:
    """Point features in the frame defined by some of them, with information.

    Attributes:
        dim: 2 or 3.
        frame_ids: the ids of ``F_O, F_X`` (2D) or ``F_O, F_X, F_Y`` (3D).
        ids: ``(m,)`` ids of the other features.
        x: ``(r + m d,)`` state: the ``r`` free frame coordinates, then each other feature.
        info: information matrix of ``x`` (dense or CSR).
        name: label for messages.
    """

    dim: int
    frame_ids: tuple[int, ...]
    ids: IntArray
    x: FloatArray
    info: FloatArray | sp.csr_matrix
    name: str = "feature map"

    def __post_init__(self) -> None:
        k = n_frame_features(self.dim)
        who = f"feature-only map {self.name!r}"
        if len(self.frame_ids) != k or len(set(self.frame_ids)) != k:
            raise InvalidMapError(f"{who}: a {self.dim}D frame needs {k} distinct features, got {self.frame_ids}")
        if np.intersect1d(self.ids, np.array(self.frame_ids)).size:
            raise InvalidMapError(f"{who}: frame features {self.frame_ids} are also listed as variables")
        n = n_reduced(self.dim) + self.dim * self.ids.size
        if self.x.shape != (n,) or self.info.shape != (n, n):
            raise InvalidMapError(f"{who}: state {self.x.shape} / information {self.info.shape}, expected ({n},)")

    @property
    def all_ids(self) -> IntArray:
        """Every feature id: frame features first."""
        return np.concatenate([np.array(self.frame_ids, dtype=np.int64), self.ids])

    @property
    def state_dim(self) -> int:
        """Length of the state vector."""
        return int(self.x.size)

    def full(self) -> FloatArray:
        """Return full coordinates ``(N, d)`` of every feature (frame features first)."""
        return expand_reduced(self.dim, self.x)

    def positions(self) -> dict[int, FloatArray]:
        """Return ``{id: position}`` of every feature, in this map's frame."""
        return dict(zip(self.all_ids.tolist(), self.full()))


def expand_reduced(dim: int, x: FloatArray) -> FloatArray:
    """Return full coordinates ``(N, d)`` from a reduced state (frame features first)."""
    mask = _free_mask(dim)
    r = int(mask.sum())
    frame = np.zeros(mask.shape)
    frame[mask] = x[:r]
    return np.vstack([frame, x[r:].reshape(-1, dim)])


def reduce_full(dim: int, full: FloatArray) -> FloatArray:
    """Return the reduced state of full coordinates (inverse of :func:`expand_reduced`)."""
    mask = _free_mask(dim)
    k = mask.shape[0]
    return np.concatenate([full[:k][mask], full[k:].ravel()])


def expansion_matrix(dim: int, n_features: int) -> sp.csr_matrix:
    """Return ``E`` with ``full.ravel() = E @ reduced`` (zeros for the fixed coordinates)."""
    mask = np.concatenate([_free_mask(dim).ravel(), np.ones((n_features - n_frame_features(dim)) * dim, dtype=bool)])
    rows = np.flatnonzero(mask)
    return sp.csr_matrix((np.ones(rows.size), (rows, np.arange(rows.size))), shape=(mask.size, rows.size))


# --------------------------------------------------------------------------- frames


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
    info = g.T @ info_old @ g
    info = info.toarray() if sp.issparse(info) and info.shape[0] <= DENSE_MAX else info
    if not sp.issparse(info):
        info = 0.5 * (np.asarray(info) + np.asarray(info).T)
    return FeatureMap(d, new_frame_ids, ids_new[k:], x_new, info, fmap.name)


# ----------------------------------------------------------------- pose-feature -> feature-only


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


def to_feature_only(local_map: LocalMap, frame_ids: Sequence[int] | None = None) -> FeatureMap:
    """Convert a pose-feature local map into a feature-only map (Sec. 3.2, 8.3).

    All poses are marginalised out (Schur complement), including the frame pose: the features
    are re-parametrised as ``(frame pose in the feature frame, features in the feature frame)``,
    an exact change of variables, and the frame pose is then marginalised too.

    Raises:
        GeometryError: fewer than 2 (3) features, or degenerate frame features.
    """
    d = local_map.dim
    info = to_dense(local_map.info)
    feats = np.flatnonzero(local_map.kinds == FEATURE)
    poses = np.flatnonzero(local_map.kinds == POSE)
    f_idx = local_map.scalar_index(feats)
    p_idx = local_map.scalar_index(poses)
    if p_idx.size:
        i_ff = info[np.ix_(f_idx, f_idx)]
        i_fp = info[np.ix_(f_idx, p_idx)]
        info_f = i_ff - i_fp @ np.linalg.solve(info[np.ix_(p_idx, p_idx)], i_fp.T)
    else:
        info_f = info[np.ix_(f_idx, f_idx)]
    ids = local_map.ids[feats]
    full_r = local_map.x[f_idx].reshape(-1, d)  # features seen from the frame pose
    positions = dict(zip(ids.tolist(), full_r))
    frame_ids = tuple(frame_ids) if frame_ids is not None else choose_frame_features(d, positions, ids.tolist())
    full_perm, ids_perm, perm = _reorder(d, full_r, ids, frame_ids)
    k = n_frame_features(d)
    rot = frame_rotation(d, full_perm[0], full_perm[1], full_perm[2] if d == 3 else None)
    feat_frame = (full_perm - full_perm[0]) @ rot.T  # features in the feature frame
    x_red = reduce_full(d, feat_frame)
    # The frame pose T in the feature frame sees each feature at R_T (X - t_T), with R_T = R^T
    # and t_T = -R F_O: the features' old coordinates as a function of (T, features in the new
    # frame). T's rotation is parametrised by a perturbation R_T (I + [delta]x), not by Euler
    # angles, which are singular when the features lie in a plane facing the robot (Simu3D).
    r_t = rot.T
    t_t = -rot @ full_perm[0]
    n = ids.size
    rel = feat_frame - t_t  # X - t_T
    p = d + (1 if d == 2 else 3)
    jac = np.zeros((n * d, p + x_red.size))
    for i in range(n):
        block = jac[i * d : (i + 1) * d]
        block[:, :d] = -r_t
        if d == 2:
            block[:, 2] = drot2(np.arctan2(r_t[0, 1], r_t[0, 0])) @ rel[i]
        else:
            rx = np.array([[0.0, -rel[i, 2], rel[i, 1]], [rel[i, 2], 0.0, -rel[i, 0]], [-rel[i, 1], rel[i, 0], 0.0]])
            block[:, d:p] = -r_t @ rx
    res_d_point = np.broadcast_to(r_t, (n, d, d))
    e = expansion_matrix(d, n).toarray()
    jac[:, p:] = sp.block_diag(list(res_d_point)).toarray() @ e
    row_perm = (perm[:, None] * d + np.arange(d)).ravel()
    info_perm = info_f[np.ix_(row_perm, row_perm)]
    params = jac.T @ info_perm @ jac
    info_fo = params[p:, p:] - params[p:, :p] @ np.linalg.solve(params[:p, :p], params[:p, p:])
    return FeatureMap(d, tuple(int(f) for f in frame_ids), ids_perm[k:], x_red, 0.5 * (info_fo + info_fo.T), local_map.name)


# ----------------------------------------------------------------------- joining


def common_features(a: FeatureMap, b: FeatureMap) -> list[int]:
    """Return the ids of features both maps hold (frame features included), in ``a``'s order."""
    in_b = set(b.all_ids.tolist())
    return [f for f in a.all_ids.tolist() if f in in_b]


def join_feature_maps(a: FeatureMap, b: FeatureMap, name: str = "global") -> FeatureMap:
    """Join two feature-only maps by linear least squares in a shared feature frame (Sec. 7.2).

    Both maps move to the frame of the longest-baseline common features (the farthest pair, and
    in 3D the common feature farthest from their line; :func:`choose_frame_features`), even when
    one map's own frame is common: the linearisation error of a change of frame grows with the
    uncertainty of the new frame's direction, which a short baseline inflates. Keeping ``b``'s
    own frame (usually a short one: ``b`` is a small local map) gave a feature RMSE of 0.68 m
    against the Nonlinear LS on VicPark200 D&C; the longest baseline gives 0.13 m.

    Raises:
        GeometryError: fewer than 2 (3 non-collinear) common features.
    """
    if a.dim != b.dim:
        raise InvalidMapError(f"cannot join a {a.dim}D feature map with a {b.dim}D one")
    frame = choose_frame_features(a.dim, a.positions(), common_features(a, b))
    a, b = change_feature_frame(a, frame), change_feature_frame(b, frame)
    r = n_reduced(a.dim)
    d = a.dim
    pos_a = {int(f): i for i, f in enumerate(a.ids.tolist())}
    new_ids = [int(f) for f in b.ids.tolist() if int(f) not in pos_a]
    union_var = [r + d * pos_a[int(f)] if int(f) in pos_a else -1 for f in b.ids.tolist()]
    next_new = r + d * a.ids.size
    b_to_union = list(range(r))  # the frame's free coordinates are common
    for off in union_var:
        if off < 0:
            off = next_new
            next_new += d
        b_to_union.extend(range(off, off + d))
    n = next_new
    x, info = solve_union(a.info, a.x, b.info, b.x, np.array(b_to_union, dtype=np.int64), n)
    return FeatureMap(d, tuple(a.frame_ids), np.concatenate([a.ids, np.array(new_ids, dtype=np.int64)]), x, info, name)


def _timed_join(a: FeatureMap, b: FeatureMap, on_join: Callable[[float], None] | None) -> FeatureMap:
    t0 = time.perf_counter()
    joined = join_feature_maps(a, b)
    if on_join is not None:
        on_join(time.perf_counter() - t0)
    return joined


def join_features_sequential(maps: Sequence[FeatureMap], on_join: Callable[[float], None] | None = None) -> FeatureMap:
    """Join feature-only maps one at a time (``on_join`` gets each join's seconds)."""
    if not maps:
        raise InvalidMapError("no feature maps to join")
    result = maps[0]
    for m in maps[1:]:
        result = _timed_join(result, m, on_join)
    return result


def join_features_dc(maps: Sequence[FeatureMap], on_join: Callable[[float], None] | None = None) -> FeatureMap:
    """Join feature-only maps by divide and conquer (neighbours paired level by level)."""
    if not maps:
        raise InvalidMapError("no feature maps to join")
    level = list(maps)
    while len(level) > 1:
        nxt = [_timed_join(level[i], level[i + 1], on_join) for i in range(0, len(level) - 1, 2)]
        if len(level) % 2:
            nxt.append(level[-1])
        level = nxt
    return level[0]


def precondition(maps: Sequence[LocalMap]) -> list[LocalMap]:
    """Merge consecutive pose-feature maps until neighbours share enough features (Sec. 8.3).

    Consecutive groups must share at least 2 features (3 non-collinear in 3D); a map that does
    not share enough with the current group is joined into it as a pose-feature map (Linear
    SLAM), and the merged group is returned in the frame of its start pose.
    """
    groups: list[LocalMap] = []
    current: Group | None = None
    for m in maps:
        closed, current = precondition_step(current, m)
        if closed is not None:
            groups.append(closed)
    if current is not None:
        groups.append(current.closed())
    return groups


@dataclass(frozen=True)
class Group:
    """Consecutive pose-feature maps being merged until the next one shares a feature frame.

    Attributes:
        merged: the maps joined so far (in the frame of the newest end pose).
        start_id: the first map's frame pose: the group is reported in its frame.
    """

    merged: LocalMap
    start_id: int

    def closed(self) -> LocalMap:
        """Return the group in the frame of its start pose."""
        return self.merged if self.merged.frame_id == self.start_id else change_frame(self.merged, self.start_id)


def precondition_step(group: Group | None, submap: LocalMap) -> tuple[LocalMap | None, Group]:
    """Take the next pose-feature map: close the group if the map shares a frame with it, else merge.

    Returns:
        ``(closed group or None, the open group)``.

    Raises:
        LinearSlamError: the map cannot be merged into the group (e.g. not consecutive).
    """
    if group is None:
        return None, Group(submap, submap.frame_id)
    shared = np.intersect1d(group.merged.feature_ids, submap.feature_ids)
    if _frame_possible(submap.dim, group.merged, shared):
        return group.closed(), Group(submap, submap.frame_id)
    name = group.merged.name.rstrip("+") + "+"
    return None, Group(join_pair(group.merged, submap, name=name), group.start_id)


def _frame_possible(dim: int, local_map: LocalMap, shared: IntArray) -> bool:
    if shared.size < n_frame_features(dim):
        return False
    if dim == 2:
        return True
    pos = {int(local_map.ids[i]): local_map.x[local_map.scalar_slice(i)] for i in np.flatnonzero(local_map.kinds == FEATURE)}
    try:
        choose_frame_features(dim, pos, shared.tolist())
    except GeometryError:
        return False
    return True


__all__ = [
    "FeatureMap",
    "FeatureRefineResult",
    "change_feature_frame",
    "choose_frame_features",
    "feature_residuals",
    "feature_rmse",
    "refine_features",
    "frame_rotation",
    "join_feature_maps",
    "join_features_dc",
    "join_features_sequential",
    "precondition",
    "reframe_features",
    "to_feature_only",
]


# ------------------------------------------------------------------ Nonlinear LS (I-DMJ)


@dataclass(frozen=True)
class FeatureRefineResult:
    """Gauss-Newton optimum of all feature-only maps together (I-DMJ's optimum)."""

    map: FeatureMap
    chi2: float
    chi2_history: tuple[float, ...]
    iterations: int


def feature_residuals(
    layout: FeatureMap, x: FloatArray, maps: Sequence[FeatureMap], jacobian: bool = True
) -> tuple[FloatArray, sp.csr_matrix | None]:
    """Return the stacked residuals ``g_i(X) - x_i`` of every map and ``d/dX`` (X: ``layout``'s state).

    ``g_i`` expresses the global features map ``i`` holds in map ``i``'s frame, reduced.

    Raises:
        FrameError: a map holds a feature the layout does not.
    """
    d = layout.dim
    k = n_frame_features(d)
    full = expand_reduced(d, x)
    row_of = {int(f): i for i, f in enumerate(layout.all_ids.tolist())}
    n_full = full.shape[0] * d
    res, blocks = [], []
    for m in maps:
        try:
            rows = np.array([row_of[int(f)] for f in m.all_ids.tolist()], dtype=np.int64)
        except KeyError as exc:
            raise FrameError(f"feature {exc.args[0]} of map {m.name!r} is not in map {layout.name!r}") from None
        local, jac_local = reframe_features(d, full[rows], list(range(k)))
        res.append(reduce_full(d, local) - m.x)
        if jacobian:
            cols = (rows[:, None] * d + np.arange(d)).ravel()
            sel = sp.csr_matrix((np.ones(cols.size), (np.arange(cols.size), cols)), shape=(cols.size, n_full))
            blocks.append(expansion_matrix(d, rows.size).T @ jac_local @ sel)
    r = np.concatenate(res)
    if not jacobian:
        return r, None
    jac = (sp.vstack(blocks, format="csr") @ expansion_matrix(d, full.shape[0])).tocsr()
    return r, jac


def refine_features(initial: FeatureMap, maps: Sequence[FeatureMap], max_iterations: int = 50) -> FeatureRefineResult:
    """Gauss-Newton on ``sum_i ||g_i(X) - x_i||^2_{I_i}`` from ``initial`` (its frame stays fixed)."""
    from linear_slam_ros.core.solvers import solve_sparse_spd

    weight = sp.block_diag([sp.csr_matrix(to_dense(m.info)) for m in maps], format="csr")
    x = initial.x.copy()
    r, jac = feature_residuals(initial, x, maps)
    chi2 = float(r @ (weight @ r))
    history = [chi2]
    it = 0
    for it in range(1, max_iterations + 1):
        assert jac is not None
        hessian = (jac.T @ weight @ jac).tocsr()
        dx = solve_sparse_spd(hessian, -(jac.T @ (weight @ r)))
        step = 1.0
        for _ in range(20):
            r_try, jac_try = feature_residuals(initial, x + step * dx, maps)
            chi2_try = float(r_try @ (weight @ r_try))
            if chi2_try <= chi2 * (1 + 1e-12) + 1e-12:
                break
            step *= 0.5
        else:
            break
        decrease = chi2 - chi2_try
        x, r, jac, chi2 = x + step * dx, r_try, jac_try, chi2_try
        history.append(chi2)
        if np.abs(step * dx).max() < 1e-10 or decrease <= 1e-13 * max(chi2, 1e-300):
            break
    assert jac is not None
    hessian = (jac.T @ weight @ jac).tocsr()
    result = FeatureMap(initial.dim, initial.frame_ids, initial.ids, x, hessian, initial.name)
    return FeatureRefineResult(result, chi2, tuple(history), it)


def feature_rmse(a: FeatureMap, b: FeatureMap) -> float:
    """Per-coordinate RMSE of the features both maps hold; both must share a frame.

    Raises:
        FrameError: different frames.
    """
    if tuple(a.frame_ids) != tuple(b.frame_ids):
        raise FrameError(f"RMSE needs one frame: frames {a.frame_ids} and {b.frame_ids}")
    pa, pb = a.positions(), b.positions()
    common = sorted(set(pa) & set(pb))
    diff = np.stack([pa[f] - pb[f] for f in common])
    return float(np.sqrt(np.sum(diff * diff) / diff.size))
