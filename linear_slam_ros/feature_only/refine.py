"""Feature-only Nonlinear LS (I-DMJ's optimum): Gauss-Newton over every feature-only map."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
import scipy.sparse as sp

from linear_slam_ros.core.errors import FrameError
from linear_slam_ros.core.feature_frames import expand_reduced, n_frame_features, reduce_full
from linear_slam_ros.core.least_squares import gauss_newton
from linear_slam_ros.core.local_map import to_dense
from linear_slam_ros.feature_only.frames import reframe_features
from linear_slam_ros.feature_only.maps import FeatureMap, expansion_matrix

FloatArray = npt.NDArray[np.float64]


@dataclass(frozen=True)
class FeatureRefineResult:
    """Gauss-Newton optimum of all feature-only maps together (I-DMJ's optimum)."""

    map: FeatureMap
    chi2: float
    chi2_history: tuple[float, ...]
    iterations: int


def feature_residuals(
    layout: FeatureMap, x: FloatArray, maps: Sequence[FeatureMap], jacobian: bool = True
) -> tuple[FloatArray, sp.csr_matrix | None]:
    """Return the stacked residuals ``g_i(X) - x_i`` of every map and ``d/dX`` (X: ``layout``'s state).

    ``g_i`` expresses the global features map ``i`` holds in map ``i``'s frame, reduced.

    Raises:
        FrameError: a map holds a feature the layout does not.
    """
    d = layout.dim
    k = n_frame_features(d)
    full = expand_reduced(d, x)
    row_of = {int(f): i for i, f in enumerate(layout.all_ids.tolist())}
    n_full = full.shape[0] * d
    res, blocks = [], []
    for m in maps:
        try:
            rows = np.array([row_of[int(f)] for f in m.all_ids.tolist()], dtype=np.int64)
        except KeyError as exc:
            raise FrameError(f"feature {exc.args[0]} of map {m.name!r} is not in map {layout.name!r}") from None
        local, jac_local = reframe_features(d, full[rows], list(range(k)))
        res.append(reduce_full(d, local) - m.x)
        if jacobian:
            cols = (rows[:, None] * d + np.arange(d)).ravel()
            sel = sp.csr_matrix((np.ones(cols.size), (np.arange(cols.size), cols)), shape=(cols.size, n_full))
            blocks.append(expansion_matrix(d, rows.size).T @ jac_local @ sel)
    r = np.concatenate(res)
    if not jacobian:
        return r, None
    jac = (sp.vstack(blocks, format="csr") @ expansion_matrix(d, full.shape[0])).tocsr()
    return r, jac


def refine_features(initial: FeatureMap, maps: Sequence[FeatureMap], max_iterations: int = 50) -> FeatureRefineResult:
    """Gauss-Newton on ``sum_i ||g_i(X) - x_i||^2_{I_i}`` from ``initial`` (its frame stays fixed)."""
    weight = sp.block_diag([sp.csr_matrix(to_dense(m.info)) for m in maps], format="csr")

    def residuals(x: FloatArray) -> tuple[FloatArray, sp.csr_matrix]:
        r, jac = feature_residuals(initial, x, maps)
        assert jac is not None
        return r, jac

    gn = gauss_newton(residuals, weight, initial.x, max_iterations=max_iterations)
    hessian = (gn.jacobian.T @ weight @ gn.jacobian).tocsr()
    result = FeatureMap(initial.dim, initial.frame_ids, initial.ids, gn.x, hessian, initial.name)
    return FeatureRefineResult(result, gn.chi2, gn.chi2_history, gn.iterations)


def feature_rmse(a: FeatureMap, b: FeatureMap) -> float:
    """Per-coordinate RMSE of the features both maps hold; both must share a frame.

    Raises:
        FrameError: different frames.
    """
    if tuple(a.frame_ids) != tuple(b.frame_ids):
        raise FrameError(f"RMSE needs one frame: frames {a.frame_ids} and {b.frame_ids}")
    pa, pb = a.positions(), b.positions()
    common = sorted(set(pa) & set(pb))
    diff = np.stack([pa[f] - pb[f] for f in common])
    return float(np.sqrt(np.sum(diff * diff) / diff.size))
