"""Frames defined by point features (Linear SLAM App. B): their features, rotation and derivatives.

A frame is defined by ``F_O`` (origin) and ``F_X`` (x axis), and in 3D ``F_Y`` (x-y plane). The
frame features' fixed coordinates leave a state: in 2D ``F_O = (0, 0)`` and ``F_X = (x, 0)`` keep
one scalar; in 3D ``F_O = 0``, ``F_X = (x, 0, 0)``, ``F_Y = (x, y, 0)`` keep three. Used by the
feature-only maps (:mod:`linear_slam_ros.feature_only`) and by joins of pose-feature maps that
share features only (:mod:`linear_slam_ros.joining.feature_frame`).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import numpy.typing as npt

from linear_slam_ros.core.errors import GeometryError
from linear_slam_ros.core.geometry import drot2, rot2

FloatArray = npt.NDArray[np.float64]

_DEGENERATE = 1e-6
"""Relative length below which frame features count as coincident (or collinear): the frame's
direction, and so a map converted into it, is conditioned as (scale / baseline)^2, which at 1e-6
is 1e12, near what double precision solves (at 1e-8 the conversion's normal equations were
singular)."""


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
        raise GeometryError(f"frame features F_O, F_X, F_Y are collinear or coincident (|(F_X - F_O) x (F_Y - F_O)| = {n3:.3g})")
    v2 = np.cross(v3, v1)
    return np.stack([v1 / n1, v2 / np.linalg.norm(v2), v3 / n3])


def rotation_derivatives(dim: int, origin: FloatArray, x_feat: FloatArray, y_feat: FloatArray | None) -> list[FloatArray]:
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


def choose_frame_features(dim: int, positions: dict[int, FloatArray], candidates: Sequence[int]) -> tuple[int, ...]:
    """Pick well-conditioned frame features among ``candidates``: the farthest pair (2D), then in
    3D the third feature farthest from their line.

    The frame they define passes :func:`frame_rotation`'s checks, so a map can be converted into it.

    Raises:
        GeometryError: too few candidates, or all of them degenerate: coincident (the farthest two
            less than :data:`_DEGENERATE` times the coordinates' scale apart) or, in 3D, collinear.
    """
    cand = [int(c) for c in candidates]
    k = n_frame_features(dim)
    if len(cand) < k:
        raise GeometryError(f"a {dim}D frame needs {k} common features, only {len(cand)} available: {cand}")
    pts = np.array([positions[c] for c in cand])
    dist = np.linalg.norm(pts[:, None, :] - pts[None, :, :], axis=-1)
    i, j = np.unravel_index(int(np.argmax(dist)), dist.shape)
    if dist[i, j] < _DEGENERATE * max(1.0, float(np.abs(pts).max())):
        raise GeometryError(f"common features {cand} all coincide (at most {dist[i, j]:.3g} m apart)")
    if dim == 2:
        return (cand[i], cand[j])
    axis = (pts[j] - pts[i]) / dist[i, j]
    off = pts - pts[i]
    perp = np.linalg.norm(off - np.outer(off @ axis, axis), axis=1)
    m = int(np.argmax(perp))
    if perp[m] <= _DEGENERATE * dist[i, j]:
        raise GeometryError(f"common features {cand} are collinear")
    frame_rotation(dim, pts[i], pts[j], pts[m])
    return (cand[i], cand[j], cand[m])
