"""The map-joining objective of eq. (7) over many local maps: residuals, Jacobian, weights.

Each local map ``i`` is an observation of the global variables it holds, expressed in the frame
of its frame pose: ``e_i = h_i(X) - x_i`` with ``h_i`` the change into that pose's frame and pose
angle rows wrapped into ``(-pi, pi]``. The objective is ``sum_i e_i^T I_i e_i`` (the χ² of the
datasets README). The global state ``X`` is a :class:`LocalMap`'s state in the frame of an
origin pose that is not a variable.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
import scipy.sparse as sp

from linear_slam_ros.core.errors import FrameError
from linear_slam_ros.core.geometry import points_to_frame, pose_size, poses_to_frame, wrap_angle
from linear_slam_ros.core.local_map import POSE, LocalMap, block_diagonal, pose_key

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]


def _block_triplets(
    row_starts: IntArray, nrows: int, col_starts: IntArray, ncols: int, blocks: FloatArray
) -> tuple[IntArray, IntArray, FloatArray]:
    r = np.broadcast_to(row_starts[:, None, None] + np.arange(nrows)[None, :, None], blocks.shape)
    c = np.broadcast_to(col_starts[:, None, None] + np.arange(ncols)[None, None, :], blocks.shape)
    return r.ravel(), c.ravel(), blocks.ravel()


@dataclass(frozen=True, eq=False)
class MapObjective:
    """Eq. (7) summed over local maps, for a fixed global variable layout.

    Build with :meth:`build`. Attributes are index arrays over "records" (one per variable of
    each local map) split into feature and pose records.
    """

    dim: int
    n_state: int
    origin_id: int
    z: FloatArray
    weight: sp.csr_matrix
    angle_rows: npt.NDArray[np.bool_]
    feat_rows: IntArray
    feat_cols: IntArray
    feat_ref: IntArray
    pose_rows: IntArray
    pose_cols: IntArray
    pose_ref: IntArray

    @classmethod
    def build(cls, layout: LocalMap, maps: Sequence[LocalMap]) -> MapObjective:
        """Index every local map's variables into ``layout``'s state.

        Args:
            layout: a map whose variables include every variable and frame pose of ``maps``
                (other than its own frame pose, the fixed origin).
            maps: the local maps.

        Raises:
            FrameError: a local map's variable or frame pose is missing from ``layout``.
        """
        dim = layout.dim
        lookup = layout.key_set
        offsets = layout.offsets
        feat_rows, feat_cols, feat_ref, pose_rows, pose_cols, pose_ref = [], [], [], [], [], []
        zs, infos, angle_rows = [], [], []
        row = 0
        for m in maps:
            if m.frame_id == layout.frame_id:
                ref = -1
            else:
                ref_idx = lookup.get(pose_key(m.frame_id))
                if ref_idx is None:
                    raise FrameError(f"frame pose {m.frame_id} of map {m.name!r} is not in map {layout.name!r}")
                ref = int(offsets[ref_idx])
            # the layout's own frame pose is the fixed origin: index -2, no columns
            origin_key = pose_key(layout.frame_id)
            pos = np.fromiter(
                (-2 if k == origin_key else lookup.get(k, -1) for k in m.keys.tolist()), np.int64, count=m.n_vars
            )
            if np.any(pos == -1):
                missing = int(m.ids[pos == -1][0])
                raise FrameError(f"variable {missing} of map {m.name!r} is not in map {layout.name!r}")
            rows = row + m.offsets
            is_pose = m.kinds == POSE
            pose_rows.append(rows[is_pose])
            pose_pos = pos[is_pose]
            pose_cols.append(np.where(pose_pos >= 0, offsets[np.maximum(pose_pos, 0)], -1))
            pose_ref.append(np.full(int(is_pose.sum()), ref))
            feat_rows.append(rows[~is_pose])
            feat_cols.append(offsets[pos[~is_pose]])
            feat_ref.append(np.full(int((~is_pose).sum()), ref))
            zs.append(m.x)
            infos.append(m.info)
            angle_rows.append(m.angles)
            row += m.state_dim
        cat = lambda parts: np.concatenate(parts).astype(np.int64) if parts else np.zeros(0, np.int64)  # noqa: E731
        return cls(
            dim=dim,
            n_state=layout.state_dim,
            origin_id=layout.frame_id,
            z=np.concatenate(zs),
            weight=block_diagonal(infos),
            angle_rows=np.concatenate(angle_rows),
            feat_rows=cat(feat_rows),
            feat_cols=cat(feat_cols),
            feat_ref=cat(feat_ref),
            pose_rows=cat(pose_rows),
            pose_cols=cat(pose_cols),
            pose_ref=cat(pose_ref),
        )

    def _frames(self, x: FloatArray, ref: IntArray) -> tuple[FloatArray, FloatArray]:
        """Gather poses starting at offsets ``ref`` (``-1``: the origin, a zero pose)."""
        p = pose_size(self.dim)
        frames = np.zeros((ref.size, p))
        has = ref >= 0
        frames[has] = x[ref[has, None] + np.arange(p)]
        return frames[:, : self.dim], frames[:, self.dim :]

    def residuals(self, x: FloatArray, jacobian: bool = False) -> tuple[FloatArray, sp.csr_matrix | None]:
        """Return the stacked residual ``h(X) - z`` (angles wrapped) and optionally ``dh/dX``."""
        d, p = self.dim, pose_size(self.dim)
        r = np.empty_like(self.z)
        parts: list[tuple[IntArray, int, IntArray, int, FloatArray]] = []  # (row starts, rows, col starts, cols, blocks)
        if self.feat_rows.size:
            t_f, a_f = self._frames(x, self.feat_ref)
            pts = x[self.feat_cols[:, None] + np.arange(d)]
            res = points_to_frame(d, t_f, a_f, pts)
            idx = self.feat_rows[:, None] + np.arange(d)
            r[idx] = res.points
            if jacobian:
                parts.append((self.feat_rows, d, self.feat_cols, d, np.ascontiguousarray(res.d_point)))
                has = self.feat_ref >= 0
                parts.append((self.feat_rows[has], d, self.feat_ref[has], p, res.d_frame[has]))
        if self.pose_rows.size:
            t_f, a_f = self._frames(x, self.pose_ref)
            t_v, a_v = self._frames(x, self.pose_cols)  # the origin (-1) is the zero pose
            res_p = poses_to_frame(d, t_f, a_f, t_v, a_v)
            idx = self.pose_rows[:, None] + np.arange(p)
            r[idx[:, :d]] = res_p.translations
            r[idx[:, d:]] = res_p.angles
            if jacobian:
                var = self.pose_cols >= 0
                parts.append((self.pose_rows[var], p, self.pose_cols[var], p, res_p.d_pose[var]))
                has = self.pose_ref >= 0
                parts.append((self.pose_rows[has], p, self.pose_ref[has], p, res_p.d_frame[has]))
        r -= self.z
        r[self.angle_rows] = wrap_angle(r[self.angle_rows])
        if not jacobian:
            return r, None
        return r, self._jacobian(parts)

    def _jacobian(self, parts: list[tuple[IntArray, int, IntArray, int, FloatArray]]) -> sp.csr_matrix:
        """The Jacobian's CSR matrix from its blocks, as ``csr_matrix((vals, (rows, cols)))`` builds it.

        Its pattern depends on the index records alone, so it is worked out at the first call
        (scipy's conversion of the triplets, on their positions) and kept: later calls (every
        step of a refinement round) only permute the blocks' values into it. The same arrays as
        scipy's conversion, bit for bit, as no two triplets share an entry (else scipy sums them,
        and its conversion is used every time).
        """
        shape = (self.z.size, self.n_state)
        vals = np.concatenate([blocks.ravel() for *_, blocks in parts])
        pattern: tuple[IntArray, npt.NDArray[np.integer], npt.NDArray[np.integer]] | None = self.__dict__.get(
            "_jacobian_pattern"
        )
        if pattern is None:
            trip = [_block_triplets(*part) for part in parts]
            rows = np.concatenate([t[0] for t in trip])
            cols = np.concatenate([t[1] for t in trip])
            probe = sp.csr_matrix((np.arange(rows.size, dtype=np.float64), (rows, cols)), shape=shape)
            if probe.nnz < rows.size:  # repeated entries: scipy's conversion sums them, every time
                return sp.csr_matrix((vals, (rows, cols)), shape=shape)
            pattern = (probe.data.astype(np.int64), probe.indices, probe.indptr)
            self.__dict__["_jacobian_pattern"] = pattern  # a cache of the frozen value's records
        order, indices, indptr = pattern
        jac = sp.csr_matrix((vals[order], indices.copy(), indptr.copy()), shape=shape)
        jac.has_canonical_format = True
        return jac

    def chi2(self, x: FloatArray) -> float:
        """Return ``sum_i e_i^T I_i e_i`` at state ``x``."""
        r, _ = self.residuals(x)
        return float(r @ (self.weight @ r))


def chi2(global_map: LocalMap, maps: Sequence[LocalMap]) -> float:
    """Return the χ² of a joined map against all local maps (eq. 7 summed over every map).

    The joined map may be in any frame that is one of its poses or the maps' first frame; its
    estimate is moved to the frame of ``maps[0]``'s frame pose first (its information is not used).
    """
    from linear_slam_ros.core.frames import estimate_in_frame

    origin = maps[0].frame_id
    layout = estimate_in_frame(global_map, origin) if global_map.frame_id != origin else global_map
    return MapObjective.build(layout, maps).chi2(layout.x)
