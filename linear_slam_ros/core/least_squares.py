"""Sparse Gauss-Newton with step halving: the loop behind every Nonlinear LS of the project.

The callers (pose and pose-feature maps in :mod:`linear_slam_ros.evaluation.nonlinear`,
feature-only maps in :mod:`linear_slam_ros.feature_only.refine`) supply the residual function,
its Jacobian, the weight (the local maps' information, block diagonal) and how a step is applied
(angles wrapped, for instance); the loop is the same for all.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
import scipy.sparse as sp

from linear_slam_ros.core.solvers import solve_sparse_spd

logger = logging.getLogger(__name__)

FloatArray = npt.NDArray[np.float64]
Residuals = Callable[[FloatArray], tuple[FloatArray, sp.csr_matrix]]
"""``x -> (r, J)``: stacked residuals ``(k,)`` and their Jacobian ``(k, n)`` at ``x``."""

MAX_HALVINGS = 20
"""Largest number of times a step that raises the objective is halved."""


@dataclass(frozen=True)
class GaussNewtonResult:
    """Where Gauss-Newton stopped.

    Attributes:
        x: ``(n,)`` the estimate.
        jacobian: ``(k, n)`` Jacobian of the residuals at ``x``.
        chi2: weighted squared residual at ``x``.
        chi2_history: the objective before each iteration and at the end.
        iterations: iterations taken.
        converged: the step or the decrease fell below its tolerance, or no step decreased the
            objective any more (a minimum to machine precision).
    """

    x: FloatArray
    jacobian: sp.csr_matrix
    chi2: float
    chi2_history: tuple[float, ...]
    iterations: int
    converged: bool


def gauss_newton(
    residuals: Residuals,
    weight: sp.csr_matrix | sp.csr_array,
    x0: FloatArray,
    apply_step: Callable[[FloatArray, FloatArray], FloatArray] | None = None,
    max_iterations: int = 50,
    step_tol: float = 1e-10,
    chi2_rtol: float = 1e-13,
) -> GaussNewtonResult:
    """Minimise ``r(x)^T W r(x)`` from ``x0``; steps that raise it are halved (up to 20 times).

    Args:
        residuals: ``x -> (r, J)``.
        weight: ``(k, k)`` symmetric positive semi-definite weight ``W``.
        x0: ``(n,)`` starting estimate.
        apply_step: ``(x, dx) -> x'`` (default ``x + dx``), e.g. to wrap angles.
        max_iterations: iteration cap.
        step_tol: stop when the largest step component is below this (units of ``x``).
        chi2_rtol: stop when the objective's relative decrease is below this.

    Raises:
        SolverError: the normal equations ``J^T W J`` are singular.
    """
    x = np.array(x0, dtype=np.float64)
    r, jac = residuals(x)
    chi2 = float(r @ (weight @ r))
    history = [chi2]
    converged = False
    it = 0
    for it in range(1, max_iterations + 1):
        step = gauss_newton_step(residuals, weight, x, r, jac, chi2, apply_step)
        if step is None:
            logger.info("Gauss-Newton: no decrease along the step at iteration %d; stopping", it)
            converged = True
            break
        decrease = chi2 - step.chi2
        x, r, jac, chi2 = step.x, step.r, step.jacobian, step.chi2
        history.append(chi2)
        logger.debug("Gauss-Newton iteration %d: chi2 %.6f, max step %.3g", it, chi2, step.max_step)
        if step.max_step < step_tol or decrease <= chi2_rtol * max(chi2, 1e-300):
            converged = True
            break
    return GaussNewtonResult(x, jac, chi2, tuple(history), it, converged)


@dataclass(frozen=True)
class GaussNewtonStep:
    """One accepted Gauss-Newton step (:func:`gauss_newton_step`).

    Attributes:
        x: ``(n,)`` the new estimate.
        r: ``(k,)`` residuals at ``x``.
        jacobian: ``(k, n)`` their Jacobian at ``x``.
        chi2: ``r^T W r`` at ``x``.
        max_step: largest component of the step taken (after halving), units of ``x``.
    """

    x: FloatArray
    r: FloatArray
    jacobian: sp.csr_matrix
    chi2: float
    max_step: float


def gauss_newton_step(
    residuals: Residuals,
    weight: sp.csr_matrix | sp.csr_array,
    x: FloatArray,
    r: FloatArray,
    jac: sp.csr_matrix,
    chi2: float,
    apply_step: Callable[[FloatArray, FloatArray], FloatArray] | None = None,
    solve: Callable[[sp.csr_matrix, FloatArray], FloatArray] | None = None,
) -> GaussNewtonStep | None:
    """Take one Gauss-Newton step from ``x`` (residuals ``r``, Jacobian ``jac``, objective ``chi2`` there).

    The step solves ``J^T W J dx = -J^T W r``; a step that raises the objective is halved, up to
    :data:`MAX_HALVINGS` times. This is the iteration of :func:`gauss_newton`, for callers that
    decide between iterations what to do next (the online refiner).

    ``solve`` solves the SPD normal equations (default :func:`solve_sparse_spd`; the online
    refiner passes one that keeps CHOLMOD's analysis across the steps of a round).

    Returns:
        The accepted step, or ``None`` when no halving decreased the objective (a minimum to
        machine precision).

    Raises:
        SolverError: the normal equations ``J^T W J`` are singular.
    """
    hessian = (jac.T @ (weight @ jac)).tocsr()
    dx = (solve or solve_sparse_spd)(hessian, -(jac.T @ (weight @ r)))
    scale = 1.0
    for _ in range(MAX_HALVINGS):
        x_try = x + scale * dx if apply_step is None else apply_step(x, scale * dx)
        r_try, jac_try = residuals(x_try)
        chi2_try = float(r_try @ (weight @ r_try))
        if chi2_try <= chi2 * (1 + 1e-12) + 1e-12:
            return GaussNewtonStep(x_try, r_try, jac_try, chi2_try, float(np.abs(scale * dx).max()) if dx.size else 0.0)
        scale *= 0.5
    return None
