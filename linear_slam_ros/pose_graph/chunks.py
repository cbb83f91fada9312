"""Pose-graph chunks: the relative-pose constraints of one submap, and their local maps.

A chunk is a set of edges ``(from, to, z, I)``: pose ``to`` measured from pose ``from`` as
``z`` (``x y phi`` / ``x y z alpha beta gamma``, the datasets' convention) with ``p x p``
information ``I``. A *star* chunk (every edge leaves one pose, as in the benchmark pose-only
datasets) is already a pose-only local map in the frame of that pose: its estimate is the
measurements, its information block diagonal, with repeated edges fused. Other chunks need a
closed-form estimate of their own (LAGO, 2D) before they can be joined.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
import scipy.linalg

from linear_slam_ros.core.errors import GraphError, InvalidMapError
from linear_slam_ros.core.geometry import pose_size
from linear_slam_ros.core.local_map import POSE, LocalMap, default_end_pose, fuse_repeated

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]


@dataclass(frozen=True, eq=False)
class PoseGraphChunk:
    """Relative-pose constraints of one submap.

    Attributes:
        dim: 2 or 3.
        seq: sequence number of the chunk.
        from_ids: ``(k,)`` pose ids the measurements are taken from.
        to_ids: ``(k,)`` pose ids measured.
        measurements: ``(k, p)`` pose ``to`` seen from pose ``from`` (m, rad).
        information: ``(k, p, p)`` symmetric positive-definite information of each edge.
    """

    dim: int
    seq: int
    from_ids: IntArray
    to_ids: IntArray
    measurements: FloatArray
    information: FloatArray

    def __post_init__(self) -> None:
        who = f"pose-graph chunk {self.seq}"
        if self.dim not in (2, 3):
            raise GraphError(f"{who}: dimension must be 2 or 3, got {self.dim}")
        p = pose_size(self.dim)
        k = self.from_ids.shape[0] if np.ndim(self.from_ids) == 1 else -1
        if k < 1 or np.shape(self.to_ids) != (k,):
            raise GraphError(f"{who}: needs at least one edge and equal numbers of from and to ids")
        if np.shape(self.measurements) != (k, p) or np.shape(self.information) != (k, p, p):
            raise GraphError(
                f"{who}: {k} edges need measurements ({k}, {p}) and information ({k}, {p}, {p}), got "
                f"{np.shape(self.measurements)} and {np.shape(self.information)}"
            )
        if np.any(self.from_ids < 0) or np.any(self.to_ids < 0):
            raise GraphError(f"{who}: pose ids must be >= 0")
        loops = np.flatnonzero(self.from_ids == self.to_ids)
        if loops.size:
            raise GraphError(f"{who}: edge {int(loops[0])} connects pose {int(self.from_ids[loops[0]])} to itself")
        if not (np.all(np.isfinite(self.measurements)) and np.all(np.isfinite(self.information))):
            raise GraphError(f"{who}: non-finite measurement or information")
        for e in range(k):
            block = self.information[e]
            if not np.allclose(block, block.T, rtol=1e-9, atol=0):
                raise GraphError(f"{who}: information of edge {e} ({int(self.from_ids[e])}->{int(self.to_ids[e])}) is not symmetric")
            try:
                scipy.linalg.cholesky(block)
            except np.linalg.LinAlgError:
                raise GraphError(
                    f"{who}: information of edge {e} ({int(self.from_ids[e])}->{int(self.to_ids[e])}) is not positive definite"
                ) from None

    @property
    def n_edges(self) -> int:
        """Number of edges."""
        return int(self.from_ids.shape[0])

    @property
    def is_star(self) -> bool:
        """Whether every edge leaves the same pose."""
        return bool(np.all(self.from_ids == self.from_ids[0]))


def star_chunk_to_local_map(chunk: PoseGraphChunk) -> LocalMap:
    """Return the pose-only local map of a star chunk, in the frame of its centre pose.

    Raises:
        GraphError: the chunk is not a star.
    """
    if not chunk.is_star:
        raise GraphError(
            f"pose-graph chunk {chunk.seq} is not a star (edges leave poses {sorted(set(chunk.from_ids.tolist()))[:5]}): "
            "it needs a closed-form estimate (LAGO) first"
        )
    frame = int(chunk.from_ids[0])
    p = pose_size(chunk.dim)
    kinds = np.full(chunk.n_edges, POSE, dtype=np.int8)
    info = scipy.linalg.block_diag(*chunk.information)
    ids, kinds, values, info = chunk.to_ids.astype(np.int64), kinds, chunk.measurements.reshape(-1), info
    name = f"pose_graph chunk {chunk.seq}"
    if np.unique(ids).size != ids.size:
        ids, kinds, values, info = fuse_repeated(name, chunk.dim, ids, kinds, values, info)
    assert values.size == ids.size * p
    try:
        return LocalMap(chunk.dim, frame, default_end_pose(frame, ids), ids, kinds, values, info, name=name)
    except InvalidMapError as exc:
        raise GraphError(str(exc)) from None


def chunk_to_local_map(chunk: PoseGraphChunk) -> LocalMap:
    """Return the pose-only local map of a chunk, in the frame of its first edge's ``from`` pose.

    Star chunks convert exactly; other 2D chunks go through LAGO when it is available.

    Raises:
        GraphError: the chunk cannot be converted (the message says why).
    """
    if chunk.is_star:
        return star_chunk_to_local_map(chunk)
    try:
        from linear_slam_ros.pose_graph.lago import lago_local_map  # issue 4: closed-form 2D pose graphs
    except ImportError:
        raise GraphError(
            f"pose-graph chunk {chunk.seq} is not a star and this build has no LAGO: only star chunks are accepted"
        ) from None
    return lago_local_map(chunk)
