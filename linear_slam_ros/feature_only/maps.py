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

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
import scipy.sparse as sp

from linear_slam_ros.core.errors import InvalidMapError
from linear_slam_ros.core.feature_frames import _free_mask, expand_reduced, n_frame_features, n_reduced

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]

_DEGENERATE = 1e-9


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
        if not self.frame_ids and not self.ids.size and not self.x.size and self.info.shape == (0, 0):
            return  # the empty map: no feature, no frame (a joiner before its first map, after a reset)
        if len(self.frame_ids) != k or len(set(self.frame_ids)) != k:
            raise InvalidMapError(f"{who}: a {self.dim}D frame needs {k} distinct features, got {self.frame_ids}")
        unique, counts = np.unique(self.ids, return_counts=True)
        if unique.size != self.ids.size:
            raise InvalidMapError(f"{who}: feature id {int(unique[counts > 1][0])} is listed more than once")
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
        return dict(zip(self.all_ids.tolist(), self.full(), strict=True))


def expansion_matrix(dim: int, n_features: int) -> sp.csr_matrix:
    """Return ``E`` with ``full.ravel() = E @ reduced`` (zeros for the fixed coordinates)."""
    mask = np.concatenate([_free_mask(dim).ravel(), np.ones((n_features - n_frame_features(dim)) * dim, dtype=bool)])
    rows = np.flatnonzero(mask)
    return sp.csr_matrix((np.ones(rows.size), (rows, np.arange(rows.size))), shape=(mask.size, rows.size))
