"""Preconditioning of pose-feature maps (Sec. 8.3): merge neighbours until they share a feature frame."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from linear_slam_ros.core.errors import GeometryError
from linear_slam_ros.core.feature_frames import choose_frame_features, n_frame_features
from linear_slam_ros.core.frames import change_frame
from linear_slam_ros.core.local_map import FEATURE, LocalMap
from linear_slam_ros.joining.pairwise import join_pair

IntArray = npt.NDArray[np.int64]


def precondition(maps: Sequence[LocalMap]) -> list[LocalMap]:
    """Merge consecutive pose-feature maps until neighbours share enough features (Sec. 8.3).

    Consecutive groups must share at least 2 features (3 non-collinear in 3D); a map that does
    not share enough with the current group is joined into it as a pose-feature map (Linear
    SLAM), and the merged group is returned in the frame of its start pose.
    """
    groups: list[LocalMap] = []
    current: Group | None = None
    for m in maps:
        closed, current = precondition_step(current, m)
        if closed is not None:
            groups.append(closed)
    if current is not None:
        groups.append(current.closed())
    return groups


@dataclass(frozen=True)
class Group:
    """Consecutive pose-feature maps being merged until the next one shares a feature frame.

    Attributes:
        merged: the maps joined so far (in the frame of the newest end pose).
        start_id: the first map's frame pose: the group is reported in its frame.
    """

    merged: LocalMap
    start_id: int

    def closed(self) -> LocalMap:
        """Return the group in the frame of its start pose."""
        return self.merged if self.merged.frame_id == self.start_id else change_frame(self.merged, self.start_id)


def precondition_step(group: Group | None, submap: LocalMap) -> tuple[LocalMap | None, Group]:
    """Take the next pose-feature map: close the group if the map shares a frame with it, else merge.

    Returns:
        ``(closed group or None, the open group)``.

    Raises:
        LinearSlamError: the map cannot be merged into the group (e.g. not consecutive).
    """
    if group is None:
        return None, Group(submap, submap.frame_id)
    shared = np.intersect1d(group.merged.feature_ids, submap.feature_ids)
    if _frame_possible(submap.dim, group.merged, shared):
        return group.closed(), Group(submap, submap.frame_id)
    name = group.merged.name.rstrip("+") + "+"
    return None, Group(join_pair(group.merged, submap, name=name), group.start_id)


def _frame_possible(dim: int, local_map: LocalMap, shared: IntArray) -> bool:
    """Whether the group ``local_map`` can close: the ``shared`` features define a frame in it, and so do
    all its features (the frame it is converted into, :func:`~linear_slam_ros.feature_only.conversion.to_feature_only`).

    A group whose features coincide (or are collinear in 3D) is merged with the next map instead:
    closed, it could not be converted, and neither could any later map close it.
    """
    if shared.size < n_frame_features(dim):
        return False
    pos = {int(local_map.ids[i]): local_map.x[local_map.scalar_slice(int(i))]
           for i in np.flatnonzero(local_map.kinds == FEATURE)}
    try:
        choose_frame_features(dim, pos, shared.tolist())
        choose_frame_features(dim, pos, list(pos))
    except GeometryError:
        return False
    return True
