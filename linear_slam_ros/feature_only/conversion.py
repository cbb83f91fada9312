"""Pose-feature map -> feature-only map (Sec. 3.2, 8.3): every pose marginalised, the frame pose too."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import scipy.sparse as sp

from linear_slam_ros.core.errors import GeometryError
from linear_slam_ros.core.feature_frames import choose_frame_features, frame_rotation, n_frame_features, reduce_full
from linear_slam_ros.core.geometry import drot2
from linear_slam_ros.core.local_map import FEATURE, POSE, LocalMap, to_dense
from linear_slam_ros.feature_only.frames import _reorder
from linear_slam_ros.feature_only.maps import FeatureMap, expansion_matrix


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
    positions = dict(zip(ids.tolist(), full_r, strict=True))
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
    try:
        info_fo = params[p:, p:] - params[p:, :p] @ np.linalg.solve(params[:p, :p], params[:p, p:])
    except np.linalg.LinAlgError:  # the frame features' checks keep this from happening
        raise GeometryError(
            f"map {local_map.name!r}: its frame pose is not observable from its features in the frame of {frame_ids}"
        ) from None
    return FeatureMap(d, tuple(int(f) for f in frame_ids), ids_perm[k:], x_red, 0.5 * (info_fo + info_fo.T), local_map.name)
