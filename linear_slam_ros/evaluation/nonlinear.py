"""Sparse Gauss-Newton on the map-joining objective ("Nonlinear LS", I-SLSJF), for evaluation.

Started from the Linear SLAM result it converges in a few iterations to the optimum of eq. (7)
summed over all local maps; started from the odometry chain it can stall in a wrong minimum
on long datasets (see the datasets README), which is why :func:`refine` takes an initial map.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Sequence

import numpy as np
import numpy.typing as npt

from linear_slam_ros.core.errors import SolverError
from linear_slam_ros.core.frames import change_frame
from linear_slam_ros.core.geometry import wrap_angle
from linear_slam_ros.core.local_map import LocalMap
from linear_slam_ros.evaluation.objective import MapObjective
from linear_slam_ros.core.solvers import solve_sparse_spd

logger = logging.getLogger(__name__)

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

    Steps that raise the objective are halved (up to 20 times); angles are wrapped after each step.

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
    x = initial.x.copy()
    r, jac = objective.residuals(x, jacobian=True)
    chi2 = float(r @ (objective.weight @ r))
    history = [chi2]
    converged = False
    it = 0
    for it in range(1, max_iterations + 1):
        wj = objective.weight @ jac
        hessian = (jac.T @ wj).tocsr()
        grad = jac.T @ (objective.weight @ r)
        dx = solve_sparse_spd(hessian, -grad)
        step = 1.0
        for _ in range(20):
            x_try = x + step * dx
            x_try[angles] = wrap_angle(x_try[angles])
            r_try, jac_try = objective.residuals(x_try, jacobian=True)
            chi2_try = float(r_try @ (objective.weight @ r_try))
            if chi2_try <= chi2 * (1 + 1e-12) + 1e-12:
                break
            step *= 0.5
        else:
            logger.info("Gauss-Newton: no decrease along the step at iteration %d; stopping", it)
            converged = True
            break
        decrease = chi2 - chi2_try
        x, r, jac, chi2 = x_try, r_try, jac_try, chi2_try
        history.append(chi2)
        logger.debug("Gauss-Newton iteration %d: chi2 %.6f, max step %.3g", it, chi2, np.abs(step * dx).max())
        if np.abs(step * dx).max() < step_tol or decrease <= chi2_rtol * max(chi2, 1e-300):
            converged = True
            break
    hessian = (jac.T @ (objective.weight @ jac)).tocsr()
    hessian = ((hessian + hessian.T) * 0.5).tocsr()
    if not np.all(np.isfinite(x)):
        raise SolverError("Gauss-Newton diverged to non-finite values")
    result = initial.replace(x=x, info=hessian)
    return RefineResult(result, chi2, tuple(history), it, converged)


def refine(initial: LocalMap, maps: Sequence[LocalMap], max_iterations: int = 50) -> RefineResult:
    """Refine a joined map by Gauss-Newton, in the frame of ``maps[0]``'s frame pose (pose 0)."""
    origin = maps[0].frame_id
    start = initial if initial.frame_id == origin else change_frame(initial, origin)
    return gauss_newton(start, maps, max_iterations=max_iterations)
