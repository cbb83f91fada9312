"""Feature-only (D-SLAM) joining as submaps arrive: the node's ``map_type: feature-only``.

Each pose-feature submap goes through the preconditioning of Sec. 8.3 online: consecutive
submaps are merged as pose-feature maps until the next one shares a feature frame with them (2
features in 2D, 3 non-collinear in 3D); the closed group's poses are then marginalised out
(:func:`~linear_slam_ros.feature_only.maps.to_feature_only`) and it is joined, sequentially or with
the online divide-and-conquer stack, into the feature-only global map. The open group is part of
the published map too: :func:`feature_result` joins it in on demand.

The state is one frozen value and :func:`feature_step` a pure function of (state, submap), as
for the other map kinds. After the same submaps, ``sequential`` equals
``join_features_sequential(precondition(maps))`` exactly.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, replace
from typing import Any, Sequence

import numpy as np
import scipy.sparse as sp

from linear_slam_ros.core.errors import GeometryError, InvalidMapError
from linear_slam_ros.feature_only.maps import (
    FeatureMap, Group, feature_residuals, feature_rmse, join_feature_maps, join_features_dc, join_features_sequential,
    precondition, precondition_step, refine_features, to_feature_only,
)
from linear_slam_ros.joining.pairwise import counter_push
from linear_slam_ros.core.local_map import FEATURE, LocalMap
from linear_slam_ros.evaluation.metrics import latency_summary
from linear_slam_ros.evaluation.runner import JoinMethod, peak_rss_mb

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class FeatureJoinState:
    """Feature-only joining state.

    Attributes:
        method: ``sequential`` (``stack`` holds one map) or ``online-dc`` (a binary-counter stack).
        group: the open preconditioning group (``None`` before the first submap).
        stack: joined feature-only maps of the closed groups, oldest first.
        counts: closed groups in each stack entry.
    """

    method: JoinMethod
    group: Group | None = None
    stack: tuple[FeatureMap, ...] = ()
    counts: tuple[int, ...] = ()

    @property
    def n_groups(self) -> int:
        """Closed groups joined so far."""
        return int(sum(self.counts))


def feature_step(state: FeatureJoinState, submap: LocalMap) -> FeatureJoinState:
    """Take one pose-feature submap (a pure function of state and submap).

    Raises:
        InvalidMapError: the submap holds no feature.
        LinearSlamError: the submap cannot be merged or the closed group cannot be converted or
            joined (the state is unchanged).
    """
    if not np.any(submap.kinds == FEATURE):
        raise InvalidMapError(f"submap {submap.name!r} holds no feature: map_type feature-only joins pose-feature maps")
    if state.group is not None and submap.dim != state.group.merged.dim:
        raise InvalidMapError(f"submap {submap.name!r} is {submap.dim}D, the global map is {state.group.merged.dim}D")
    closed, group = precondition_step(state.group, submap)
    if closed is None:
        return replace(state, group=group)
    fmap = to_feature_only(closed)
    if state.method is JoinMethod.SEQUENTIAL:
        joined = join_feature_maps(state.stack[0], fmap) if state.stack else fmap
        return replace(state, group=group, stack=(joined,), counts=(state.n_groups + 1,))
    stack, counts = counter_push(state.stack, state.counts, fmap, join_feature_maps)
    return replace(state, group=group, stack=stack, counts=counts)


def feature_result(state: FeatureJoinState) -> FeatureMap | None:
    """Return the global feature-only map, the open group included (``None`` if there is none).

    The open group is left out, with a debug message, while it cannot define a feature frame
    (fewer than 2 features in 2D, 3 non-collinear in 3D).
    """
    maps = list(state.stack)
    if state.group is not None:
        try:
            maps.append(to_feature_only(state.group.closed()))
        except GeometryError as exc:
            logger.debug("open group left out of the feature-only map: %s", exc)
    if not maps:
        return None
    result = maps[-1]
    for older in reversed(maps[:-1]):
        result = join_feature_maps(older, result)
    return result


@dataclass(frozen=True)
class FeatureRun:
    """A timed feature-only joining run of pose-feature local maps (CLI and benchmark).

    Attributes:
        joined: the linear result.
        refined: the feature-only Nonlinear LS from ``joined`` (I-DMJ's optimum), if asked.
        report: figures: seconds (joining only), latency, χ² (of the refined map when there is
            one, with ``linear_chi2``), RMSE of the linear result against the refined one.
    """

    joined: FeatureMap
    refined: FeatureMap | None
    report: dict[str, Any]


def run_feature_join(maps: Sequence[LocalMap], method: JoinMethod, refine_too: bool = False) -> FeatureRun:
    """Precondition, marginalise and join pose-feature maps as feature-only maps, timed.

    ``online-dc`` runs :func:`feature_step` per submap (latency per submap); ``sequential`` and
    ``dc`` convert every group first and time each pairwise join.
    """
    steps: list[float] = []
    t0 = time.perf_counter()
    if method is JoinMethod.ONLINE_DC:
        state = FeatureJoinState(JoinMethod.ONLINE_DC)
        for m in maps:
            t_step = time.perf_counter()
            state = feature_step(state, m)
            steps.append(time.perf_counter() - t_step)
        result = feature_result(state)
        if result is None:
            raise InvalidMapError("no group of the local maps defines a feature frame")
        joined = result
        seconds = time.perf_counter() - t0
        feature_maps = [to_feature_only(g) for g in precondition(maps)]  # for the objective (not timed)
    else:
        feature_maps = [to_feature_only(g) for g in precondition(maps)]
        joiner = join_features_sequential if method is JoinMethod.SEQUENTIAL else join_features_dc
        joined = joiner(feature_maps, on_join=steps.append)
        seconds = time.perf_counter() - t0
    residual, _ = feature_residuals(joined, joined.x, feature_maps, jacobian=False)
    weight = sp.block_diag([sp.csr_matrix(m.info) for m in feature_maps], format="csr")
    report: dict[str, Any] = {
        "map_type": "feature-only",
        "method": method.value,
        "n_submaps": len(maps),
        "n_feature_maps": len(feature_maps),
        "state_dim": joined.state_dim,
        "seconds": seconds,
        **latency_summary(steps),
        "latency_unit": "per submap" if method is JoinMethod.ONLINE_DC else "per pairwise join",
        "peak_rss_mb": peak_rss_mb(),
        "chi2": float(residual @ (weight @ residual)),
        "info_nnz": int(sp.csr_matrix(joined.info).count_nonzero()),
        "frame_features": list(joined.frame_ids),
    }
    refined = None
    if refine_too:
        nls = refine_features(joined, feature_maps)
        refined = nls.map
        report.update({"linear_chi2": report["chi2"], "chi2": nls.chi2, "refine_iterations": nls.iterations,
                       "rmse_feature_linear_vs_nls": feature_rmse(joined, refined)})
    return FeatureRun(joined, refined, report)
