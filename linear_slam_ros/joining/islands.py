"""Joining maps that do not chain: a common pose, or common features only (islands of a map).

When a submap is lost, or a second robot starts its own map, the submaps no longer start where
the map ends: the map falls apart into islands, each in its own frame. Two islands join as soon
as they share enough to fix their relative frame, still by linear least squares in closed form:

- a common pose: both move to that pose's frame and are joined there (eqs. 12-17);
- common point features only (2 in 2D, 3 not collinear in 3D): both move to the frame those
  features define (App. B, :mod:`~linear_slam_ros.joining.feature_frame`), are joined there, and
  the result moves to the frame of one of its poses.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from linear_slam_ros.core.errors import FrameError, GeometryError
from linear_slam_ros.core.feature_frames import choose_frame_features, n_frame_features
from linear_slam_ros.core.frames import change_frame
from linear_slam_ros.core.local_map import FEATURE, POSE, LocalMap
from linear_slam_ros.joining.feature_frame import from_feature_frame, join_feature_framed, to_feature_frame
from linear_slam_ros.joining.pairwise import GLOBAL_NAME, join_in_shared_frame, to_end_frame

logger = logging.getLogger(__name__)

IntArray = npt.NDArray[np.int64]

MAX_FRAME_CANDIDATES = 256
"""Common features searched for the best-conditioned frame (the farthest apart): enough to find a
long baseline, few enough that the O(c^2) search stays cheap."""


@dataclass(frozen=True)
class Link:
    """What two maps share that fixes their relative frame.

    Attributes:
        pose_id: a pose both hold (as a variable or as their frame), or ``None``.
        feature_ids: when no pose is shared, the common features that define the join's frame:
            ``F_O, F_X`` (2D) or ``F_O, F_X, F_Y`` (3D).
        n_common: variables both maps hold.
    """

    pose_id: int | None
    feature_ids: tuple[int, ...] = ()
    n_common: int = 0

    def describe(self) -> str:
        """One phrase for logs: ``"common pose 12"`` or ``"common features (3, 8)"``."""
        return f"common pose {self.pose_id}" if self.pose_id is not None else f"common features {self.feature_ids}"


def poses_of(local_map: LocalMap) -> IntArray:
    """Return the map's pose ids, its frame pose included (sorted)."""
    return np.union1d(local_map.pose_ids, [local_map.frame_id]).astype(np.int64)


def find_link(map_a: LocalMap, map_b: LocalMap) -> Link | None:
    """Return how two maps can be joined, or ``None`` when they share too little.

    A common pose wins (the larger map's frame pose if the other holds it, so that only the smaller
    map changes frame; then the smaller map's; then the newest common pose); else at least
    :func:`~linear_slam_ros.core.feature_frames.n_frame_features` common features not all
    coincident (nor, in 3D, collinear), the frame chosen for the longest baseline
    (:func:`~linear_slam_ros.core.feature_frames.choose_frame_features`).
    """
    if map_a.dim != map_b.dim:
        return None
    common_poses = np.intersect1d(poses_of(map_a), poses_of(map_b))
    common_features = np.intersect1d(map_a.feature_ids, map_b.feature_ids)
    n_common = int(common_poses.size + common_features.size)
    if common_poses.size:
        # the larger map's frame pose if the other holds it (only the smaller map moves), then the smaller's
        larger, smaller = (map_a, map_b) if map_a.state_dim >= map_b.state_dim else (map_b, map_a)
        frames = [f for f in (larger.frame_id, smaller.frame_id) if f in common_poses]
        return Link(int(frames[0]) if frames else int(common_poses[-1]), (), n_common)
    if common_features.size < n_frame_features(map_a.dim):
        return None
    candidates = common_features[:: max(1, -(-common_features.size // MAX_FRAME_CANDIDATES))]
    index = [map_a.index_of(2 * int(f) + FEATURE) for f in candidates]  # common: every one is in map_a
    positions = {int(f): map_a.x[map_a.scalar_slice(i)] for f, i in zip(candidates, index, strict=True) if i is not None}
    try:
        frame = choose_frame_features(map_a.dim, positions, candidates.tolist())
    except GeometryError:
        return None
    return Link(None, tuple(int(f) for f in frame), n_common)


def merge_maps(map_a: LocalMap, map_b: LocalMap, link: Link, end_id: int | None, name: str = GLOBAL_NAME) -> LocalMap:
    """Join two maps through ``link`` and return the result in the frame of pose ``end_id``.

    Args:
        map_a: one map (its variables come first in the result).
        map_b: the other.
        link: from :func:`find_link` on these maps.
        end_id: the joined map's end pose and frame (a pose of either map); ``None``: ``map_b``'s
            end pose.
        name: the joined map's name.

    Raises:
        FrameError: ``end_id`` is in neither map, or ``link`` does not fit the maps.
        GeometryError: the link's features are degenerate in ``map_b``'s estimate.
    """
    end = end_id if end_id is not None else (map_b.end_id if map_b.end_id is not None else map_a.end_id)
    if link.pose_id is not None:
        shared_a = change_frame(map_a, link.pose_id)
        shared_b = change_frame(map_b, link.pose_id)
        joined = join_in_shared_frame(shared_a, shared_b, name).replace(end_id=end)
        return to_end_frame(joined) if end is not None else joined
    if end is None:
        raise FrameError(f"maps {map_a.name!r} and {map_b.name!r} joined through features need a pose for their frame")
    framed = join_feature_framed(to_feature_frame(map_a, link.feature_ids), to_feature_frame(map_b, link.feature_ids))
    if not np.any((framed.ids == end) & (framed.kinds == POSE)):
        raise FrameError(f"pose {end} (the joined map's end pose) is in neither {map_a.name!r} nor {map_b.name!r}")
    return from_feature_frame(framed, int(end), int(end), name)


def maps_within(local_map: LocalMap, maps: Sequence[LocalMap]) -> list[LocalMap]:
    """Return the maps whose every variable and frame pose ``local_map`` holds (an island's own submaps).

    What the χ² of an island is computed over, when the submaps fell into several islands.
    """
    held = set(local_map.keys.tolist()) | {2 * local_map.frame_id}
    return [m for m in maps if 2 * m.frame_id in held and all(k in held for k in m.keys.tolist())]
