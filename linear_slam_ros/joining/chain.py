"""The newest pose from a chain of maps, without joining them: the node's fresh ``pose``.

Online divide and conquer holds the global map as a stack of joined parts, each starting where
the one before it ends (:func:`~linear_slam_ros.joining.divide_conquer.leaf_maps`). The newest
end pose in the first pose's frame is then a product of one relative pose per part
(:func:`relative_end`): cheap enough to publish on every arrival, long before the parts are
merged into the global map.
It is each part's own estimate chained together; the merged map, which also weighs the
overlaps between parts, refines it.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Protocol

import numpy as np
import numpy.typing as npt

from linear_slam_ros.core.geometry import compose_relative, relative_pose

FloatArray = npt.NDArray[np.float64]


class ChainPart(Protocol):
    """What a map in a chain provides (a ``LocalMap`` or a ``CovarianceMap``)."""

    @property
    def dim(self) -> int: ...  # noqa: D102

    @property
    def frame_id(self) -> int: ...  # noqa: D102

    @property
    def end_id(self) -> int | None: ...  # noqa: D102

    def has_pose(self, pose_id: int) -> bool: ...  # noqa: D102

    def pose(self, pose_id: int) -> FloatArray: ...  # noqa: D102


def inverse_pose(dim: int, pose: FloatArray) -> FloatArray:
    """Return the pose of the origin seen from ``pose`` (``(3,)`` or ``(6,)``)."""
    if dim == 2:  # scalar arithmetic: a numpy call per operation costs more than the arithmetic
        x, y, phi = (float(v) for v in pose)
        c, s = math.cos(phi), math.sin(phi)
        return np.array([-c * x - s * y, s * x - c * y, math.remainder(-phi, math.tau)])
    return relative_pose(dim, pose, np.zeros_like(pose))


def compose(dim: int, pose_a: FloatArray, pose_ab: FloatArray) -> FloatArray:
    """Return world pose ``b`` from world pose ``a`` and ``b`` seen from ``a`` (:func:`compose_relative` of one pose)."""
    if dim == 2:
        x, y, phi = (float(v) for v in pose_a)
        u, v, psi = (float(w) for w in pose_ab)
        c, s = math.cos(phi), math.sin(phi)
        return np.array([c * u - s * v + x, s * u + c * v + y, math.remainder(phi + psi, math.tau)])
    return compose_relative(dim, pose_a, pose_ab)


def relative_end(part: ChainPart, start_id: int) -> tuple[int, FloatArray] | None:
    """Return the part's end pose seen from pose ``start_id`` (the end of the chain before it).

    Returns:
        ``(end pose id, pose (3,) or (6,))``, or ``None`` when the part has no end pose or
        neither is in nor holds pose ``start_id``.
    """
    if part.end_id is None:
        return None
    end = part.pose(part.end_id)
    if part.frame_id == start_id:
        return part.end_id, end
    if part.has_pose(start_id):  # back from the start pose to the part's frame, then to its end
        return part.end_id, compose(part.dim, inverse_pose(part.dim, part.pose(start_id)), end)
    return None


def chain_end_pose(parts: Sequence[ChainPart], frame_pose_id: int) -> tuple[int, FloatArray] | None:
    """Return the last part's end pose in the frame of pose ``frame_pose_id``, chained along ``parts``.

    Args:
        parts: maps in order; the first is in, or holds, pose ``frame_pose_id``; each later one is
            in, or holds, the end pose of the one before it.
        frame_pose_id: the pose whose frame the result is in (the map frame: the first pose).

    Returns:
        ``(end pose id, pose (3,) or (6,) in frame_pose_id's frame)``, or ``None`` when the
        parts have no end pose or do not chain (a part neither in nor holding its predecessor's
        end pose).
    """
    end_id, pose = frame_pose_id, None
    for part in parts:
        step = relative_end(part, end_id)
        if step is None:
            return None
        end_id, pose = step[0], step[1] if pose is None else compose(part.dim, pose, step[1])
    return None if pose is None else (end_id, pose)
