"""Covariance of the newest robot pose in the map frame, from a joined map.

The node's ``pose`` output (``geometry_msgs/PoseWithCovarianceStamped``) carries the marginal
covariance of the newest end pose in the map frame (the first pose's frame).
:func:`pose_in_frame` computes it from a joined map in information form: the joint marginal of
the end pose and the map-frame pose (whichever of them is a variable: the map is held in one of
their frames), moved into the map frame to first order (the linearisation of
:func:`~linear_slam_ros.core.frames.change_frame`, so it equals the marginal of the whole map
moved to the first pose's frame, to the Jacobian's central-difference error, ~1e-7 relative).

Poses follow the datasets' convention (``x y phi`` in 2D, ``x y z alpha beta gamma`` in 3D,
metres and radians, passive rotations: README, Conventions); covariances are in those
coordinates (m², m·rad, rad²).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
import scipy.linalg.lapack
import scipy.sparse as sp

from linear_slam_ros.core.errors import FrameError, SolverError
from linear_slam_ros.core.geometry import pose_size, relative_pose, wrap_angle
from linear_slam_ros.core.local_map import LocalMap, pose_key, to_dense
from linear_slam_ros.core.solvers import DENSE_MAX, solve_sparse_spd

FloatArray = npt.NDArray[np.float64]

JACOBIAN_STEP = 1e-7
"""Central-difference step of the composition Jacobians (m, rad); their error is O(step²)."""


@dataclass(frozen=True)
class PoseEstimate:
    """A pose and its covariance in the frame of another pose.

    Attributes:
        pose_id: the pose described.
        frame_id: the pose whose frame it is in (the map frame: the first pose).
        pose: ``(3,)`` ``x y phi`` or ``(6,)`` ``x y z alpha beta gamma`` (m, rad).
        cov: ``(3, 3)`` or ``(6, 6)`` covariance in the same coordinates (m², rad²).
    """

    pose_id: int
    frame_id: int
    pose: FloatArray
    cov: FloatArray

    @property
    def dim(self) -> int:
        """2 or 3."""
        return 2 if self.pose.shape[0] == 3 else 3


def marginal_covariance(local_map: LocalMap, scalars: npt.NDArray[np.int64]) -> FloatArray:
    """Return the marginal covariance of some state scalars of a map, in the order given.

    Dense information (up to :data:`~linear_slam_ros.core.solvers.DENSE_MAX` scalars, or stored
    dense): the scalars are ordered last and one Cholesky factor ``L`` is taken; the trailing
    block ``L_ss`` gives the marginal information ``L_ss L_ss^T`` (the Schur complement), so the
    covariance is ``L_ss^-T L_ss^-1``: one LAPACK factorisation and a k x k triangular inverse
    (solving for k right-hand sides instead was up to 100 times slower on small maps with a
    multi-threaded OpenBLAS on a loaded machine). Sparse information above that size: the sparse
    solver (CHOLMOD) with k right-hand sides.

    Raises:
        SolverError: the information is not positive definite.
    """
    n, k = local_map.state_dim, scalars.size
    if n <= DENSE_MAX or not sp.issparse(local_map.info):
        dense = to_dense(local_map.info)
        others = np.ones(n, dtype=bool)
        others[scalars] = False
        order = np.concatenate([np.flatnonzero(others), scalars])
        permuted = dense[order][:, order]
        factor, status = scipy.linalg.lapack.dpotrf(permuted.T, lower=1, clean=0)  # .T: Fortran order, no copy
        if status != 0:
            raise SolverError(f"information of map {local_map.name!r} (size {n}) is not positive definite")
        inverse, status = scipy.linalg.lapack.dtrtri(factor[n - k :, n - k :], lower=1)  # reads the lower triangle
        if status != 0:  # pragma: no cover - a successful Cholesky has a non-singular diagonal
            raise SolverError(f"triangular inverse failed (LAPACK info {status}) for map {local_map.name!r}")
        inverse *= np.tri(k)  # the strict upper triangle holds what the factorisation left there
        cov = inverse.T @ inverse
    else:
        rhs = np.zeros((n, k))
        rhs[scalars, np.arange(k)] = 1.0
        cov = np.asarray(solve_sparse_spd(local_map.info, rhs)[scalars], dtype=np.float64)
    return np.asarray(0.5 * (cov + cov.T), dtype=np.float64)


def _jacobian(fn: Callable[[FloatArray], FloatArray], x: FloatArray, step: float = JACOBIAN_STEP) -> FloatArray:
    """Central-difference Jacobian of ``fn`` at ``x``, in one batched call.

    ``fn`` maps ``(k, n)`` inputs to ``(k, p)`` poses (``p`` 3 or 6); angle differences are
    wrapped, so an angle crossing +-pi between the two evaluations does not spoil a column.
    """
    n = x.shape[0]
    shifts = np.concatenate([np.eye(n), -np.eye(n)]) * step
    values = fn(x[None, :] + shifts)
    diff = values[:n] - values[n:]
    dim = 2 if diff.shape[1] == 3 else 3
    diff[:, dim:] = wrap_angle(diff[:, dim:])
    return np.asarray(diff.T / (2.0 * step), dtype=np.float64)


def pose_in_frame(local_map: LocalMap, pose_id: int, frame_pose_id: int, covariance: bool = True) -> PoseEstimate:
    """Return pose ``pose_id`` of a map, and its marginal covariance, in the frame of pose ``frame_pose_id``.

    Args:
        local_map: a joined map (information form) holding both poses, as variables or as its frame.
        pose_id: the pose wanted (the newest end pose).
        frame_pose_id: the pose whose frame the result is in (the map frame: the first pose).
        covariance: ``False`` skips the covariance (and its solve): ``cov`` is then NaN.

    Raises:
        FrameError: a pose is neither the map's frame nor one of its variables.
        SolverError: the map's information is not positive definite.
    """
    dim, p = local_map.dim, pose_size(local_map.dim)
    wanted = [pid for pid in (frame_pose_id, pose_id) if pid != local_map.frame_id]
    missing = [pid for pid in wanted if not local_map.has_pose(pid)]
    if missing:
        raise FrameError(
            f"pose {missing[0]} is neither the frame ({local_map.frame_id}) nor a variable of map {local_map.name!r}"
        )
    if pose_id == frame_pose_id:
        return PoseEstimate(pose_id, frame_pose_id, np.zeros(p), np.zeros((p, p)))
    order = sorted(set(wanted), key=lambda pid: local_map.key_set[pose_key(pid)])
    scalars = np.concatenate([local_map.scalar_index([local_map.key_set[pose_key(pid)]]) for pid in order])
    x = local_map.x[scalars]
    at = {pid: k * p for k, pid in enumerate(order)}

    def relative(values: FloatArray) -> FloatArray:  # (k, len(x)) -> (k, p): the pose seen from the frame pose
        zeros = np.zeros((values.shape[0], p))
        frame = values[:, at[frame_pose_id] : at[frame_pose_id] + p] if frame_pose_id in at else zeros
        pose = values[:, at[pose_id] : at[pose_id] + p] if pose_id in at else zeros
        return np.asarray(relative_pose(dim, frame, pose), dtype=np.float64)

    pose = relative(x[None, :])[0]
    if not covariance:
        return PoseEstimate(pose_id, frame_pose_id, pose, np.full((p, p), np.nan))
    cov = marginal_covariance(local_map, scalars)
    jac = _jacobian(relative, x)
    moved = jac @ cov @ jac.T
    return PoseEstimate(pose_id, frame_pose_id, pose, 0.5 * (moved + moved.T))
