"""Several robots in one map: each robot's pose ids kept apart, feature ids shared.

Every robot numbers its own poses from 0; two robots' pose 5 are different poses. The joiner
gives robot ``k`` (its index in the ``robots`` list, from 0) the *global* pose ids
``k * ROBOT_ID_STRIDE + id``: robot 0's ids are unchanged (a single robot's map is the same
with or without the list), robot 1's pose 5 is ``2^32 + 5``. Feature ids are shared by all
robots: the front-ends' data association says which landmark is which, and common features are
what joins the robots' maps. A front-end that measures another robot's pose (an inter-robot
loop closure) names that pose by its global id; any id at or above :data:`ROBOT_ID_STRIDE` is
taken as global already and left as it is. The published maps carry global ids.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from linear_slam_ros.core.errors import ConfigError, InvalidMapError
from linear_slam_ros.core.local_map import POSE, LocalMap

ROBOT_ID_STRIDE = 1 << 32
"""Pose ids per robot: robot ``k``'s pose ``i`` is ``k * ROBOT_ID_STRIDE + i`` in the joined map."""


def global_pose_id(slot: int, pose_id: int) -> int:
    """Return the global id of robot ``slot``'s pose ``pose_id`` (an id that is global already stays)."""
    return int(pose_id) if pose_id >= ROBOT_ID_STRIDE else slot * ROBOT_ID_STRIDE + int(pose_id)


def qualify(submap: LocalMap, slot: int) -> LocalMap:
    """Return robot ``slot``'s submap with global pose ids (features unchanged; robot 0's map as it is).

    Raises:
        ConfigError: ``slot`` is negative.
        InvalidMapError: the submap names one of the robot's poses twice, by its own id and by its
            global id (``5`` and ``2^32 + 5`` for robot 1): as a variable twice, or as its frame
            pose and a variable.
    """
    if slot < 0:
        raise ConfigError(f"robot slot {slot} must be >= 0")
    if slot == 0:
        return submap
    offset = slot * ROBOT_ID_STRIDE
    poses = submap.kinds == POSE
    local = poses & (submap.ids < ROBOT_ID_STRIDE)
    ids = np.where(local, submap.ids + offset, submap.ids)
    frame = global_pose_id(slot, submap.frame_id)
    pose_ids, counts = np.unique(ids[poses], return_counts=True)
    twice = [int(i) for i in pose_ids[counts > 1]] + ([frame] if frame in pose_ids else [])
    if twice:
        both = twice[0]
        raise InvalidMapError(
            f"robot slot {slot}: pose {both - offset} is given twice, by its own id {both - offset} and by its "
            f"global id {both}{' (frame pose and variable)' if both == frame and len(twice) == 1 else ''}"
        )
    end = None if submap.end_id is None else global_pose_id(slot, submap.end_id)
    return submap.replace(ids=ids, frame_id=frame, end_id=end)


def robot_slots(robots: Sequence[str]) -> dict[str, int]:
    """Return each robot's slot (its index in ``robots``), checking the names.

    Raises:
        ConfigError: a name is empty or not a ROS name token, or listed twice.
    """
    slots: dict[str, int] = {}
    for i, name in enumerate(robots):
        if not name or not name.isascii() or not name.replace("_", "a").isalnum() or name[0].isdigit():
            raise ConfigError(
                f"robots[{i}]={name!r} is not a robot namespace (ASCII letters, digits, '_'; not starting with a digit)"
            )
        if name in slots:
            raise ConfigError(f"robots lists {name!r} twice")
        slots[name] = i
    return slots
