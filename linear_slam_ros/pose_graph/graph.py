"""The pose-graph value: relative-pose edges between robot poses, with their information.

A pose graph is a set of edges ``(from, to, z, I)``: pose ``to`` measured from pose ``from`` as
``z`` (``x y phi`` in 2D, ``x y z alpha beta gamma`` in 3D: the datasets' convention; metres,
radians; in the frame of pose ``from``) with ``p x p`` information ``I`` (``p`` = 3 in 2D, 6
in 3D). The same type serves a whole graph (a g2o file, a dataset's edges: the input of LAGO)
and one submap's chunk of edges (a ``pose_graph`` message); its :attr:`PoseGraph.name` says
which in every error. Transport metadata (a message's ``seq`` and stamp) is not part of the
graph: the message layer carries it beside the graph.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
import scipy.linalg

from linear_slam_ros.core.errors import GraphError
from linear_slam_ros.core.geometry import canonical_angles3, pitch_lock_index, pitch_lock_message, pose_size
from linear_slam_ros.core.limits import (
    InputLimits,
    beyond_message,
    condition_fault,
    information_diagonal_fault,
    limits_or_default,
)
from linear_slam_ros.core.local_map import ID_BOUND

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]

DEFAULT_NAME = "pose graph"
"""Name of a graph built without one (error messages start with it)."""

_SYMMETRY_RTOL = 1e-9


@dataclass(frozen=True, eq=False)
class PoseGraph:
    """Relative-pose edges between robot poses; validated on construction.

    Build one with :meth:`from_edges` (array-likes, pose ids derived from the edges); the
    constructor takes the arrays as they are and checks them.

    Attributes:
        dim: 2 or 3.
        from_ids: ``(m,)`` pose ids (``>= 0``) the measurements are taken from.
        to_ids: ``(m,)`` pose ids measured; edge ``e`` measures pose ``to_ids[e]`` from pose
            ``from_ids[e]`` and never connects a pose to itself.
        measurements: ``(m, p)`` pose ``to`` in the frame of pose ``from``: ``x y phi`` (2D) or
            ``x y z alpha beta gamma`` (3D); metres, radians.
        information: ``(m, p, p)`` symmetric positive-definite information of each
            measurement, in the units of ``measurements`` (1/m², 1/(m rad), 1/rad²).
        pose_ids: ``(n,)`` every pose of the graph, sorted and unique: the poses of the edges,
            plus any vertex without edges (a g2o ``VERTEX_SE2`` no edge names).
        name: what the graph is, for messages (e.g. ``"pose-graph chunk 4"``).

    Raises:
        GraphError: any of the above does not hold (the message starts with ``name`` and
            names the edge at fault).
    """

    dim: int
    from_ids: IntArray
    to_ids: IntArray
    measurements: FloatArray
    information: FloatArray
    pose_ids: IntArray
    name: str = DEFAULT_NAME

    def __post_init__(self) -> None:
        self.validate()

    def validate(self, limits: InputLimits | None = None) -> None:
        """Check every invariant (construction does, with the default limits).

        Besides the structure, the numbers must be joinable in double precision (``limits``,
        default :data:`linear_slam_ros.core.limits.DEFAULT_LIMITS`): measured angles within
        ``max_angle``, translations within ``max_coordinate``, and each edge's information
        with its diagonal in ``[min_information, max_information]`` and its condition number
        (2-norm) at most ``max_condition``.

        Raises:
            GraphError: the first fault, naming the graph and the edge.
        """
        self._validate(limits, poses_from_edges=False)

    def _validate(self, limits: InputLimits | None, poses_from_edges: bool) -> None:
        """:meth:`validate`; ``poses_from_edges``: ``pose_ids`` is the union of the edges' ids
        (:meth:`from_edges` made it so), whose checks then hold by construction."""
        who = self.name
        if self.dim not in (2, 3):
            raise GraphError(f"{who}: dimension must be 2 or 3, got {self.dim}")
        p = pose_size(self.dim)
        k = np.shape(self.from_ids)[0] if np.ndim(self.from_ids) == 1 else -1
        if k == 0 and np.shape(self.to_ids) == (0,):
            raise GraphError(f"{who} has no edges")
        if k < 1 or np.shape(self.to_ids) != (k,):
            raise GraphError(f"{who}: needs at least one edge and equal numbers of from and to ids")
        if np.shape(self.measurements) != (k, p) or np.shape(self.information) != (k, p, p):
            raise GraphError(
                f"{who}: {k} edges need measurements ({k}, {p}) and information ({k}, {p}, {p}), got "
                f"{np.shape(self.measurements)} and {np.shape(self.information)}"
            )
        if (self.from_ids < 0).any() or (self.to_ids < 0).any() or (self.pose_ids < 0).any():
            raise GraphError(f"{who}: pose ids must be >= 0")
        for ids in (self.from_ids, self.to_ids, self.pose_ids):
            if np.size(ids) and np.max(ids) >= ID_BOUND:
                raise GraphError(f"{who}: pose id {int(np.max(ids))} is out of range (< 2**53)")
        if not poses_from_edges:
            if np.ndim(self.pose_ids) != 1 or np.any(np.diff(self.pose_ids) <= 0):
                raise GraphError(f"{who}: pose_ids must be sorted and unique")
            self._check_known_poses()
        loops = np.flatnonzero(self.from_ids == self.to_ids)
        if loops.size:
            raise GraphError(f"{who}: edge {int(loops[0])} connects pose {int(self.from_ids[loops[0]])} to itself")
        if not (np.isfinite(self.measurements).all() and np.isfinite(self.information).all()):
            raise GraphError(f"{who}: non-finite measurement or information")
        lim = limits_or_default(limits)
        self._check_measurements(lim)
        self._check_information(lim)
        object.__setattr__(self, "_checked_with", lim)  # not a field: equality ignores it

    def checked_with(self, limits: InputLimits | None) -> bool:
        """Whether this graph's numbers passed the checks of ``limits`` (default limits when None):
        the measurements' and the information's bounds, at construction or by :meth:`validate`."""
        return self.__dict__.get("_checked_with") == limits_or_default(limits)

    def _check_measurements(self, limits: InputLimits) -> None:
        """Raise :class:`GraphError` at the first measured translation beyond ``max_coordinate``,
        angle beyond ``max_angle``, or 3D rotation at the Euler angles' singularity (pitch +-90 deg,
        :data:`~linear_slam_ros.core.geometry.PITCH_LOCK_COS`)."""
        d = self.dim
        for part, what, limit_name in (
            (self.measurements[:, :d], "translation", "max_coordinate"),
            (self.measurements[:, d:], "angle", "max_angle"),
        ):
            bad = np.argwhere(np.abs(part) > float(getattr(limits, limit_name)))
            if bad.size:
                e, c = (int(v) for v in bad[0])
                where = f"measurement of edge {e} ({self._edge(e)}): {what} {c}"
                raise GraphError(f"{self.name}: {beyond_message(where, float(part[e, c]), limit_name, limits)}")
        locked = pitch_lock_index(self.measurements[:, d:]) if d == 3 else None
        if locked is not None:
            what = f"measurement of edge {locked} ({self._edge(locked)})"
            raise GraphError(f"{self.name}: {pitch_lock_message(what, abs(math.cos(self.measurements[locked, 4])))}")

    def _check_known_poses(self) -> None:
        """Raise :class:`GraphError` when an edge names a pose missing from ``pose_ids``."""
        f, t = self.from_ids, self.to_ids
        unknown = np.setdiff1d(np.union1d(f, t), self.pose_ids)
        if unknown.size:
            e = int(np.flatnonzero(np.isin(f, unknown) | np.isin(t, unknown))[0])
            raise GraphError(
                f"{self.name}: edge {e} ({int(f[e])} -> {int(t[e])}) names unknown pose {int(unknown[0])}"
                f"{f' (and {unknown.size - 1} more)' if unknown.size > 1 else ''}"
            )

    def _check_information(self, limits: InputLimits) -> None:
        """Raise :class:`GraphError` at the first edge whose information is not symmetric
        (relative tolerance 1e-9), not positive definite (no Cholesky factor), has a diagonal
        entry outside the magnitude bounds or a condition number above ``max_condition``.

        Every edge is checked at once (stacked LAPACK calls); the edge at fault is then named.
        """
        info = self.information
        transposed = np.swapaxes(info, -1, -2)
        # np.allclose(block, block.T, rtol, atol=0) of every block at once
        symmetric = np.all(np.abs(info - transposed) <= _SYMMETRY_RTOL * np.abs(transposed), axis=(1, 2))
        try:
            np.linalg.cholesky(info)
            definite = np.ones(self.n_edges, dtype=bool)
        except np.linalg.LinAlgError:  # find which (rare: a faulty message)
            definite = np.array([_has_cholesky(block) for block in info], dtype=bool)
        bad = np.flatnonzero(~(symmetric & definite))
        if bad.size:
            e = int(bad[0])
            property_ = "not symmetric" if not symmetric[e] else "not positive definite"
            raise GraphError(f"{self.name}: information of edge {e} ({self._edge(e)}) is {property_}")
        p = info.shape[1]
        diagonals = info[:, np.arange(p), np.arange(p)]
        out = np.flatnonzero(np.any((diagonals < limits.min_information) | (diagonals > limits.max_information), axis=1))
        if out.size:
            e = int(out[0])
            fault = information_diagonal_fault(diagonals[e], limits)
            raise GraphError(f"{self.name}: information of edge {e} ({self._edge(e)}): {fault or ''}")
        eigenvalues = np.linalg.eigvalsh(info)  # ascending, per edge
        smallest, largest = eigenvalues[:, 0], eigenvalues[:, -1]
        with np.errstate(divide="ignore", invalid="ignore"):
            condition = np.where(smallest > 0, largest / smallest, np.inf)
        ill = np.flatnonzero(~(condition <= limits.max_condition))
        if ill.size:
            e = int(ill[0])
            fault = condition_fault(float(condition[e]), "2-norm", limits)
            raise GraphError(f"{self.name}: information of edge {e} ({self._edge(e)}): {fault or ''}")

    def _edge(self, e: int) -> str:
        return f"{int(self.from_ids[e])}->{int(self.to_ids[e])}"

    @classmethod
    def from_edges(
        cls,
        from_ids: npt.ArrayLike,
        to_ids: npt.ArrayLike,
        measurements: npt.ArrayLike,
        information: npt.ArrayLike,
        pose_ids: npt.ArrayLike | None = None,
        *,
        dim: int | None = None,
        name: str = DEFAULT_NAME,
        limits: InputLimits | None = None,
    ) -> PoseGraph:
        """Build a graph from array-likes (ids as int64, values as float64).

        Args:
            from_ids: ``(m,)`` pose ids the measurements are taken from.
            to_ids: ``(m,)`` pose ids measured.
            measurements: ``(m, p)`` pose ``to`` seen from pose ``from`` (m, rad).
            information: ``(m, p, p)`` information of each measurement.
            pose_ids: every pose of the graph, in any order (duplicates dropped); each edge
                must name two of them. Default: the poses the edges name.
            dim: 2 or 3. Default: 3 when ``measurements`` has 6 columns, else 2.
            name: what the graph is, for messages.
            limits: the numeric bounds of :meth:`validate` (default limits when None).

        Raises:
            GraphError: shapes do not match, an edge names an unknown pose, or another
                invariant of :class:`PoseGraph` fails.
        """
        f = np.asarray(from_ids, dtype=np.int64)
        t = np.asarray(to_ids, dtype=np.int64)
        z = np.asarray(measurements, dtype=np.float64)
        info = np.asarray(information, dtype=np.float64)
        if dim is None:
            dim = 3 if z.ndim == 2 and z.shape[1] == pose_size(3) else 2
        if dim == 3 and z.ndim == 2 and z.shape[1] == pose_size(3) and info.shape == (z.shape[0], 6, 6):
            z, info = _canonical_measurements(z, info)
        poses = np.union1d(f, t) if pose_ids is None else np.unique(np.asarray(pose_ids, dtype=np.int64))
        graph = object.__new__(cls)  # the fields as they are, then one validation with ``limits``
        for field, value in (("dim", dim), ("from_ids", f), ("to_ids", t), ("measurements", z), ("information", info),
                             ("pose_ids", poses), ("name", name)):
            object.__setattr__(graph, field, value)
        graph._validate(limits, poses_from_edges=pose_ids is None)
        return graph

    @property
    def n_edges(self) -> int:
        """Number of edges."""
        return int(self.from_ids.shape[0])

    @property
    def n_poses(self) -> int:
        """Number of poses (vertices), edges' and isolated ones."""
        return int(self.pose_ids.size)

    @property
    def is_star(self) -> bool:
        """Whether every edge leaves the same pose (then the graph is a pose-only local map)."""
        return bool(np.all(self.from_ids == self.from_ids[0]))


def _canonical_measurements(z: FloatArray, info: FloatArray) -> tuple[FloatArray, FloatArray]:
    """3D measurements with canonical Euler triples, their information's ``beta`` row and column negated where
    a triple changed (as :class:`~linear_slam_ros.core.local_map.LocalMap` does; the caller's arrays unchanged)."""
    angles, flip = canonical_angles3(z[:, 3:])
    if not flip.any():
        return z, info
    z = z.copy()
    z[flip, 3:] = angles[flip]
    sign = np.ones((int(flip.sum()), 6))
    sign[:, 4] = -1.0
    info = info.copy()
    info[flip] *= sign[:, :, None] * sign[:, None, :]
    return z, info


def _has_cholesky(block: FloatArray) -> bool:
    try:
        scipy.linalg.cholesky(block)
    except np.linalg.LinAlgError:
        return False
    return True
