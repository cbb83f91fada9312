"""The joiner's newest-pose bookkeeping: the covariance of ``pose``, the stamps of the TUM trajectory.

No ROS here: the node calls a :class:`PoseTracker` under its joining lock (except
:meth:`PoseTracker.exact`, a solve on the output thread) and converts what it returns.

- With each global map the output thread computes the exact marginal covariance of the newest
  end pose in the map frame (:func:`~linear_slam_ros.core.pose_covariance.pose_in_frame`), after
  publishing the map and its views, and at most :data:`EXACT_DUTY` of the time: one sparse
  factorisation of the whole map, 0.8 s for VicPark6898's 21,292 scalars, is then computed at
  most every 8 s, while small maps get it with every global map.
- The per-arrival ``pose`` (published as soon as a submap is joined, before any global map
  includes it) carries the newest exact covariance known then, that of an earlier end pose
  (README, ``pose``): nothing is computed on the arrival path. Propagating it along the submaps
  joined since (dead reckoning: each submap's end-pose marginal, a small Cholesky, and the
  composition Jacobians) was measured at 0.33 ms of CPU per submap on VicPark200, 58 % of the
  joins' own CPU time, against a budget of a few per cent.
- Each joined submap's stamp is kept for its end pose (``path`` and ``~/save_map``'s ``poses.tum``).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from linear_slam_ros.core.errors import FrameError
from linear_slam_ros.core.local_map import LocalMap
from linear_slam_ros.core.pose_covariance import pose_in_frame

FloatArray = npt.NDArray[np.float64]

EXACT_DUTY = 0.1
"""Largest fraction of wall time spent on exact pose covariances (the output thread's other work,
the global map, comes first)."""


@dataclass
class PoseTracker:
    """End poses of submaps between arrival and join, the newest exact covariance, and the pose stamps.

    Attributes:
        pose_stamps: ``{end pose id: stamp (ns)}`` of every joined submap with an end pose (its
            message stamp; the caller's clock when that is zero).
        exact_seconds: CPU seconds spent on exact covariances (output thread).
    """

    pose_stamps: dict[int, int] = field(default_factory=dict)
    exact_seconds: float = 0.0
    _end_ids: dict[int, int | None] = field(default_factory=dict)
    _exact: FloatArray | None = None
    _exact_seq: int = -1
    _next_exact: float = 0.0
    _last_exact: bool = False

    def received(self, seq: int, end_id: int | None) -> None:
        """Record the end pose of a submap that will be offered to the joiner."""
        self._end_ids[seq] = end_id

    def joined(self, seqs: list[int], stamps: list[int]) -> None:
        """Record the stamps (ns) of the submaps just joined, one per sequence number, for their end poses."""
        for seq, stamp in zip(seqs, stamps, strict=True):
            end_id = self._end_ids.pop(seq, None)
            if end_id is not None:
                self.pose_stamps[end_id] = stamp

    def from_map(self, joined: LocalMap, first_pose_id: int) -> tuple[FloatArray, FloatArray | None] | None:
        """Return the newest end pose of a joined map in the map frame, and its covariance (no lock needed).

        The covariance is exact when one is due (:data:`EXACT_DUTY`), and then kept for the
        arrivals' poses (under the joining lock); otherwise it is the newest exact one (of an
        earlier pose), or ``None`` before any. ``None`` when the map has no end pose or does not
        hold the first pose.

        Raises:
            SolverError: the map's information is not positive definite.
        """
        if joined.end_id is None:
            return None
        try:
            self._last_exact = False
            if time.monotonic() < self._next_exact:
                return pose_in_frame(joined, joined.end_id, first_pose_id, covariance=False).pose, self.fast_covariance()
            c0, t0 = time.thread_time(), time.monotonic()
            exact = pose_in_frame(joined, joined.end_id, first_pose_id)
        except FrameError:  # the first pose is not in the map (cannot happen for joined pose maps)
            return None
        self.exact_seconds += time.thread_time() - c0
        self._last_exact = True
        now = time.monotonic()
        self._next_exact = now + (now - t0) * (1.0 / EXACT_DUTY - 1.0)
        return exact.pose, exact.cov

    def exact_due(self) -> bool:
        """Whether an exact covariance may be computed now (:data:`EXACT_DUTY`)."""
        return time.monotonic() >= self._next_exact

    @property
    def last_exact(self) -> bool:
        """Whether the last :meth:`from_map` gave the exact covariance."""
        return self._last_exact

    def set_exact(self, cov: FloatArray, last_seq: int) -> None:
        """Keep an exact covariance computed from the map of the submaps up to ``last_seq`` (under the joining lock)."""
        if last_seq >= self._exact_seq:
            self._exact, self._exact_seq = cov, last_seq

    def fast_covariance(self) -> FloatArray | None:
        """Return the newest exact covariance (of an earlier end pose), ``None`` before any."""
        return self._exact

    def forget(self, seqs: list[int]) -> None:
        """Drop the records of submaps that will not be joined (pruned numbers)."""
        for seq in seqs:
            self._end_ids.pop(seq, None)

    @property
    def pending_seqs(self) -> list[int]:
        """Sequence numbers received and not joined yet."""
        return list(self._end_ids)

    def reset(self) -> None:
        """Forget everything (``~/reset``)."""
        self._end_ids.clear()
        self.pose_stamps.clear()
        self.unknown()

    def unknown(self) -> None:
        """Forget the exact covariance (a loaded map): the next global map gives one again."""
        self._exact, self._exact_seq, self._next_exact, self._last_exact = None, -1, 0.0, False

    @staticmethod
    def pose_dim(pose: FloatArray) -> int:
        """2 or 3, from a pose's length (3 or 6)."""
        return 2 if pose.shape[0] == 3 else 3
