"""Forward loop closures held back until the chain reaches their pose, so that the χ² gate can test them.

In the pose-graph datasets most loop closures point *forward*: submap ``k`` (a star of edges from
its frame pose) holds its end pose and a pose the robot reaches later (sphere2500: every submap, 50
poses ahead; Manhattan and Intel: a third and a fifth of them). Such a pose is new to the map when
the submap arrives, so the gate has nothing to compare it with; by the time the chain reaches it
the closure is fused and a wrong one can no longer be kept out.

With the gate on (or ``hold_closures``), such a closure is split off the submap on arrival and *held*: a pose variable
that the map does not hold, that is not the submap's end pose nor between its frame pose and its end
pose (the submap's own path: pose ids run along the trajectory), and whose information is
uncoupled from the rest of the submap (an edge of its own: the information of a star pose-graph
chunk is block-diagonal per edge), so that taking it off is exact: its rows and columns are cut
out, nothing is marginalised and nothing dense is formed. A pose with one edge tells the rest of
the map nothing, so nothing is lost while it waits. It is joined, through the gate, right after
the submap whose end pose is the target, moved into the frame of that pose
(:meth:`HeldClosure.in_target_frame`: it then holds the submap's frame pose): a measurement
between two poses of the map, in the frame of the chain's end.

Holding changes the order in which the linear joins see the measurements, so the map differs from
the ungated run's even when nothing is gated (manhattanOlson3500: χ² 214.12 without holding,
173.21 with it; sphere2500 1363.77 and 1348.61; Intel 546.51 and 546.56: the README, "Gating").
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
import scipy.sparse as sp

from linear_slam_ros.core.frames import change_frame
from linear_slam_ros.core.local_map import POSE, LocalMap, pose_key

IntArray = npt.NDArray[np.int64]
FloatArray = npt.NDArray[np.float64]


@dataclass(frozen=True)
class HeldClosure:
    """A forward loop closure waiting for the chain to reach its pose: part of the joiner state.

    Attributes:
        seq: sequence number of the submap it came with; ``robot``: that submap's robot.
        name: that submap's name.
        target: id of the pose it measures (the pose the chain must reach).
        origin: id of the submap's frame pose (the pose it is measured from).
        measured: the closure as the submap measured it: in the frame of pose ``origin``, one pose
            variable, ``target``, with its information (no end pose).
    """

    seq: int
    robot: str
    name: str
    target: int
    origin: int
    measured: LocalMap

    def describe(self) -> str:
        """``loop closure 12 -> 62 of submap seq 12 ('localmap_12')``."""
        return f"loop closure {self.origin} -> {self.target} of submap seq {self.seq} ({self.name!r})"

    def in_target_frame(self) -> LocalMap:
        """The closure as it is joined: in the frame of pose ``target`` (the chain's end then), holding pose
        ``origin``; end pose ``target``. The closed-form change of frame of :attr:`measured`."""
        return change_frame(self.measured, self.target).replace(end_id=self.target, name=f"{self.name}/closure_{self.target}")


def _entries(submap: LocalMap) -> tuple[IntArray, IntArray, FloatArray]:
    """The non-zero entries ``(row, column, value)`` of the submap's information (O(non-zeros), nothing densified)."""
    if sp.issparse(submap.info):
        coo = submap.info.tocoo()
        keep = coo.data != 0.0
        return coo.row[keep].astype(np.int64), coo.col[keep].astype(np.int64), coo.data[keep]
    dense = np.asarray(submap.info)
    rows, cols = np.nonzero(dense)
    return rows.astype(np.int64), cols.astype(np.int64), dense[rows, cols]


def _uncoupled(owner: IntArray, rows: IntArray, cols: IntArray, n_vars: int) -> npt.NDArray[np.bool_]:
    """Which variables' information has no entry coupling them with another variable (``owner``: variable of each scalar)."""
    coupled = np.zeros(n_vars, dtype=bool)
    coupled[owner[rows[owner[rows] != owner[cols]]]] = True
    return ~coupled


def _closures(submap: LocalMap, forward: list[int], entries: tuple[IntArray, IntArray, FloatArray],
              owner: IntArray) -> list[LocalMap]:
    """Each uncoupled variable of ``forward`` alone, with its block of the information (one pass over the entries)."""
    rows, cols, values = entries
    offsets = np.concatenate([[0], np.cumsum(submap.sizes)])
    slot = np.full(submap.n_vars, -1, dtype=np.int64)
    slot[forward] = np.arange(len(forward))
    size = int(submap.sizes[forward[0]])  # poses of one map: one size
    blocks = np.zeros((len(forward), size, size))
    mine = slot[owner[rows]] >= 0  # uncoupled: their entries are all in their own block
    r, c = rows[mine], cols[mine]
    var = owner[r]
    blocks[slot[var], r - offsets[var], c - offsets[var]] = values[mine]
    return [submap.restricted([i], blocks[j]) for j, i in enumerate(forward)]


def _select(submap: LocalMap, var_indices: list[int]) -> LocalMap:
    """Return the variables ``var_indices`` of ``submap`` with their rows and columns of the information.

    Exact when they are uncoupled from the others; a sparse information stays sparse.
    """
    scalars = submap.scalar_index(np.asarray(var_indices, dtype=np.int64))
    info = submap.info[scalars][:, scalars] if sp.issparse(submap.info) else np.asarray(submap.info)[np.ix_(scalars, scalars)]
    return submap.restricted(var_indices, info)


def split_forward(
    submap: LocalMap, known: Callable[[int], bool], seq: int, robot: str = ""
) -> tuple[LocalMap | None, tuple[HeldClosure, ...]]:
    """Take a submap's forward loop closures off it (module docstring).

    Args:
        submap: the arriving submap, in its frame pose's frame.
        known: whether the map holds the variable of a key (:func:`~linear_slam_ros.core.local_map.pose_key`).
        seq: the submap's sequence number; ``robot``: its robot (recorded in each held closure).

    Returns:
        The submap without them (the same object when there is none; ``None`` when nothing is
        left), and the held closures, in the submap's variable order.
    """
    if submap.end_id is None:
        return submap, ()
    end_key = pose_key(submap.end_id)
    new = [i for i, (key, kind) in enumerate(zip(submap.keys.tolist(), submap.kinds.tolist(), strict=True))
           if kind == POSE and key != end_key and not known(key)]
    if not new:
        return submap, ()
    entries = _entries(submap)
    owner = np.repeat(np.arange(submap.n_vars), submap.sizes)
    alone = _uncoupled(owner, entries[0], entries[1], submap.n_vars)
    # a pose between the frame pose and the end pose is the submap's own path (a star chunk of several steps),
    # not a closure: held, it would wait for a chain end that passes it by (pose ids run along the trajectory)
    low, high = sorted((submap.frame_id, submap.end_id))
    forward = [i for i in new if alone[i] and not low < int(submap.ids[i]) < high]
    if not forward:
        return submap, ()
    held = [HeldClosure(seq, robot, submap.name, int(submap.ids[i]), submap.frame_id, closure)
            for i, closure in zip(forward, _closures(submap, forward, entries, owner), strict=True)]
    others = sorted(set(range(submap.n_vars)) - set(forward))
    return (_select(submap, others) if others else None), tuple(held)


def without_held(
    maps: Sequence[LocalMap], numbers: Sequence[tuple[str, int]], held: Sequence[HeldClosure]
) -> list[LocalMap]:
    """Return ``maps`` with each closure still held cut out of the submap it came with (exact: it is uncoupled).

    What the joined map's objective covers when a stream ends with closures whose pose was never
    reached: they were never joined, so the χ² and the refinement leave them out. A submap left
    with no variable is dropped.

    Args:
        maps: the local maps, as offered (feature ids as joined: poses are what matters here).
        numbers: each map's ``(robot, sequence number)``, as offered.
        held: the closures held at the end (``JoinerState.held``).

    Raises:
        KeyError: a closure's submap is not among ``numbers``.
    """
    where = {number: i for i, number in enumerate(numbers)}
    targets: dict[int, set[int]] = {}
    for closure in held:
        targets.setdefault(where[(closure.robot, closure.seq)], set()).add(closure.target)
    out: list[LocalMap | None] = list(maps)
    for i, poses in targets.items():
        m = maps[i]
        keep = [j for j, (pid, kind) in enumerate(zip(m.ids.tolist(), m.kinds.tolist(), strict=True))
                if not (kind == POSE and pid in poses)]
        out[i] = _select(m, keep) if keep else None
    return [m for m in out if m is not None]


__all__ = ["HeldClosure", "split_forward", "without_held"]
