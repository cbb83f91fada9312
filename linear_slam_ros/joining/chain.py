"""The newest pose from a chain of maps, without joining them: the node's fresh ``pose``.

Online divide and conquer holds the global map as a stack of joined parts, each starting where
the one before it ends (:func:`~linear_slam_ros.joining.divide_conquer.leaf_maps`). The newest
end pose in the first pose's frame is then a product of one relative pose per part: cheap
enough to publish on every arrival, long before the parts are merged into the global map.
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


class PoseChain:
    """:func:`chain_end_pose` that remembers its last chain, so a call redoes only the parts that changed.

    Online D&C's stack changes at its top: from one arrival to the next, the older parts are the
    same objects, so their chained end poses are reused (the cache holds the parts themselves,
    so an identity cannot be reused by a new object while it is cached).
    """

    def __init__(self) -> None:
        self._parts: list[ChainPart] = []
        self._ends: list[tuple[int, FloatArray]] = []
        self._frame_pose_id: int | None = None

    def end_pose(self, parts: Sequence[ChainPart], frame_pose_id: int) -> tuple[int, FloatArray] | None:
        """Return what :func:`chain_end_pose` returns, reusing the common prefix of the last call."""
        keep = 0
        if frame_pose_id == self._frame_pose_id:
            for old, new in zip(self._parts, parts, strict=False):
                if old is not new:
                    break
                keep += 1
        self._parts, self._ends, self._frame_pose_id = list(parts[:keep]), self._ends[:keep], frame_pose_id
        start = self._ends[-1] if self._ends else (frame_pose_id, None)
        for part in parts[keep:]:
            end = _chain_step(part, *start)
            if end is None:
                return None
            self._parts.append(part)
            self._ends.append(end)
            start = end
        return self._ends[-1] if self._ends else None


def _chain_step(part: ChainPart, end_id: int, t_end: FloatArray | None) -> tuple[int, FloatArray] | None:
    """Move the chain's end (``end_id`` at world pose ``t_end``; ``None``: the origin) across one part."""
    dim = part.dim
    if t_end is None:
        t_end = np.zeros(3 if dim == 2 else 6)
    if part.frame_id == end_id:
        t_frame = t_end
    elif part.has_pose(end_id):  # the part's frame seen from the world: end, then back from end to frame
        t_frame = compose(dim, t_end, inverse_pose(dim, part.pose(end_id)))
    else:
        return None
    if part.end_id is None:
        return None
    return part.end_id, compose(dim, t_frame, part.pose(part.end_id))


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
    end: tuple[int, FloatArray | None] = (frame_pose_id, None)
    for part in parts:
        step = _chain_step(part, *end)
        if step is None:
            return None
        end = step
    return None if end[1] is None else (end[0], end[1])
