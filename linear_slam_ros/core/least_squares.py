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
        hessian = (jac.T @ (weight @ jac)).tocsr()
        dx = solve_sparse_spd(hessian, -(jac.T @ (weight @ r)))
        step = 1.0
        for _ in range(MAX_HALVINGS):
            x_try = x + step * dx if apply_step is None else apply_step(x, step * dx)
            r_try, jac_try = residuals(x_try)
            chi2_try = float(r_try @ (weight @ r_try))
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
    return GaussNewtonResult(x, jac, chi2, tuple(history), it, converged)
