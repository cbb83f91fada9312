"""Feature-only (D-SLAM) joining as submaps arrive: the node's ``map_type: feature-only``.

Each pose-feature submap goes through the preconditioning of Sec. 8.3 online: consecutive
submaps are merged as pose-feature maps until the next one shares a feature frame with them (2
features in 2D, 3 non-collinear in 3D); the closed group's poses are then marginalised out
(:func:`~linear_slam_ros.feature_only.conversion.to_feature_only`) and it is joined, into one
map (sequential) or onto the online divide-and-conquer stack, to form the feature-only global
map. The open group is part of the published map too: :func:`feature_result` joins it in on
demand.

The state is one frozen value and :func:`feature_step` a pure function of (state, submap), as
for the other map kinds. After the same submaps, sequential joining equals
``join_features_sequential(precondition(maps))`` exactly.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, replace

import numpy as np

from linear_slam_ros.core.errors import GeometryError, InvalidMapError
from linear_slam_ros.core.local_map import FEATURE, LocalMap
from linear_slam_ros.feature_only.conversion import to_feature_only
from linear_slam_ros.feature_only.joining import join_feature_maps
from linear_slam_ros.feature_only.maps import FeatureMap
from linear_slam_ros.feature_only.precondition import Group, precondition_step
from linear_slam_ros.joining.divide_conquer import counter_push, merge_stack

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class FeatureJoinState:
    """Feature-only joining state.

    Attributes:
        group: the open preconditioning group (``None`` before the first submap).
        stack: joined feature-only maps of the closed groups, oldest first (one map when joining
            sequentially, a binary-counter stack with divide and conquer).
        counts: closed groups in each stack entry.
    """

    group: Group | None = None
    stack: tuple[FeatureMap, ...] = ()
    counts: tuple[int, ...] = ()

    @property
    def n_groups(self) -> int:
        """Closed groups joined so far."""
        return int(sum(self.counts))


def feature_step(state: FeatureJoinState, submap: LocalMap, divide_and_conquer: bool) -> FeatureJoinState:
    """Take one pose-feature submap (a pure function of state and submap).

    Args:
        state: the state so far.
        submap: a pose-feature local map.
        divide_and_conquer: push closed groups on a binary-counter stack instead of joining them
            into one map.

    A submap that sees no feature (odometry alone, a stretch without landmarks) is merged into
    the open group through its poses, as the offline preconditioning does: refusing it broke the
    chain of frames, and every later submap was refused. Only while the map holds no feature yet
    is such a submap refused (nothing is lost: the map starts at the next one's frame; a pose-graph
    stream is refused that way).

    Raises:
        InvalidMapError: the submap holds no feature while the map holds none yet, or its
            dimension differs from the map's.
        LinearSlamError: the submap cannot be merged or the closed group cannot be converted or
            joined (the state is unchanged).
    """
    if state.group is None and not state.stack and not np.any(submap.kinds == FEATURE):
        raise InvalidMapError(
            f"submap {submap.name!r} holds no feature, and the map none yet: map_type feature-only joins pose-feature maps"
        )
    if state.group is not None and submap.dim != state.group.merged.dim:
        raise InvalidMapError(f"submap {submap.name!r} is {submap.dim}D, the global map is {state.group.merged.dim}D")
    closed, group = precondition_step(state.group, submap)
    if closed is None:
        return replace(state, group=group)
    fmap = to_feature_only(closed)
    if not divide_and_conquer:
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
    return merge_stack(maps, join_feature_maps) if maps else None
