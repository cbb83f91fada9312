"""Sparse Gauss-Newton on the map-joining objective ("Nonlinear LS", I-SLSJF), for evaluation.

Started from the Linear SLAM result it converges in a few iterations to the optimum of eq. (7)
summed over all local maps; started from the odometry chain it can stall in a wrong minimum
on long datasets (see the datasets README), which is why :func:`refine` takes an initial map.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
import scipy.sparse as sp

from linear_slam_ros.core import least_squares
from linear_slam_ros.core.errors import SolverError
from linear_slam_ros.core.frames import change_frame
from linear_slam_ros.core.geometry import wrap_angle
from linear_slam_ros.core.local_map import LocalMap
from linear_slam_ros.evaluation.objective import MapObjective

FloatArray = npt.NDArray[np.float64]


@dataclass(frozen=True)
class RefineResult:
    """Result of Gauss-Newton refinement.

    Attributes:
        map: the optimum, in the frame of the initial layout, with information ``J^T W J``.
        chi2: objective at the optimum.
        chi2_history: objective before each iteration and at the end.
        iterations: Gauss-Newton steps taken.
        converged: whether the step fell below the tolerance.
    """

    map: LocalMap
    chi2: float
    chi2_history: tuple[float, ...]
    iterations: int
    converged: bool


def gauss_newton(
    initial: LocalMap,
    maps: Sequence[LocalMap],
    max_iterations: int = 50,
    step_tol: float = 1e-10,
    chi2_rtol: float = 1e-13,
) -> RefineResult:
    """Minimise ``sum_i e_i^T I_i e_i`` over the variables of ``initial``, in ``initial``'s frame.

    The loop is :func:`linear_slam_ros.core.least_squares.gauss_newton`; angles are wrapped after each step.

    Args:
        initial: variables and starting estimate; its frame pose is held fixed.
        maps: local maps observing those variables.
        max_iterations: iteration cap.
        step_tol: stop when ``max |dx|`` is below this (m or rad).
        chi2_rtol: stop when the objective's relative decrease is below this.

    Raises:
        FrameError: a map's variable or frame pose is not in ``initial``.
        SolverError: the normal equations are singular.
    """
    objective = MapObjective.build(initial, maps)
    angles = initial.angles

    def apply_step(x: FloatArray, dx: FloatArray) -> FloatArray:
        x_new = x + dx
        x_new[angles] = wrap_angle(x_new[angles])
        return x_new

    def residuals(x: FloatArray) -> tuple[FloatArray, sp.csr_matrix]:
        r, jac = objective.residuals(x, jacobian=True)
        assert jac is not None
        return r, jac

    gn = least_squares.gauss_newton(
        residuals, objective.weight, initial.x, apply_step, max_iterations, step_tol, chi2_rtol
    )
    jac = gn.jacobian
    hessian = (jac.T @ (objective.weight @ jac)).tocsr()
    hessian = ((hessian + hessian.T) * 0.5).tocsr()
    if not np.all(np.isfinite(gn.x)):
        raise SolverError("Gauss-Newton diverged to non-finite values")
    result = initial.replace(x=gn.x, info=hessian)
    return RefineResult(result, gn.chi2, gn.chi2_history, gn.iterations, gn.converged)


def refine(initial: LocalMap, maps: Sequence[LocalMap], max_iterations: int = 50) -> RefineResult:
    """Refine a joined map by Gauss-Newton, in the frame of ``maps[0]``'s frame pose (pose 0)."""
    origin = maps[0].frame_id
    start = initial if initial.frame_id == origin else change_frame(initial, origin)
    return gauss_newton(start, maps, max_iterations=max_iterations)
