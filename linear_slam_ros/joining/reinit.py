"""Re-initialising a feature whose sightings keep failing the χ² gate: a failed data association, repaired.

When the gate splits a feature's sighting off a submap, the map keeps its older estimate of that
feature. If the front-end's landmark has become a different point from the one the map holds (a
wrong association upstream, an object moved), its next sightings agree with the one split off and
disagree with the map, and each would be split off in turn: a cascade (VicPark6898: 22 of its 45
gated submaps). So a feature whose sighting was split off is *suspect*; if the next submap that
sees it fails on it too, the feature is re-initialised: from that submap on, the front-end's id
names a new landmark (id :data:`RELABEL_BASE` minus a count, an id no front-end may use), which
that sighting starts, while the map's old landmark keeps what it had. A suspect whose next
sighting passes is cleared: one wrong sighting (the gate's case) changes nothing afterwards.

A front-end does the same when an association fails. Only features are re-initialised: a pose
that fails is a loop closure, and the chain goes on through it. The relabels are one value for
the whole map: with several robots sharing feature ids, a re-initialisation renames every
robot's later sightings of that feature.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np

from linear_slam_ros.core.errors import InvalidMapError
from linear_slam_ros.core.local_map import FEATURE, LocalMap, seed_key_lookup, var_keys
from linear_slam_ros.joining.gate import GateResult, marginalise_out

RELABEL_BASE = -(1 << 40)
"""Feature ids at or below this name re-initialised landmarks (the joiner's); a front-end's submap carrying one
is refused, with the gate on or off (it may be turned on later). Re-initialisation ``k`` (from 0) gets id ``RELABEL_BASE - k``."""


@dataclass(frozen=True)
class Relabels:
    """Which front-end feature ids name re-initialised landmarks, and which are suspect: part of the joiner state.

    Attributes:
        aliases: ``(front-end id, landmark id)`` of each re-initialisation, oldest first (a feature
            re-initialised twice has two; the later one is current).
        suspects: front-end ids whose latest sighting was split off by the gate, sorted.
    """

    aliases: tuple[tuple[int, int], ...] = ()
    suspects: tuple[int, ...] = ()

    @functools.cached_property
    def _current(self) -> dict[int, int]:
        """Front-end id -> the landmark id its sightings join now."""
        return dict(self.aliases)

    @functools.cached_property
    def _front(self) -> dict[int, int]:
        """Landmark id -> the front-end id it stands for."""
        return {landmark: front for front, landmark in self.aliases}

    def front_id(self, feature_id: int) -> int:
        """Return the front-end id of a feature of the map (itself unless re-initialised)."""
        return self._front.get(feature_id, feature_id)

    def apply(self, submap: LocalMap) -> LocalMap:
        """Return ``submap`` with each re-initialised feature renamed to its current landmark id.

        Raises:
            InvalidMapError: the submap holds a feature id at or below :data:`RELABEL_BASE`.
        """
        features = submap.kinds == FEATURE
        reserved = features & (submap.ids <= RELABEL_BASE)
        if reserved.any():
            raise InvalidMapError(
                f"submap {submap.name!r}: feature id {int(submap.ids[reserved][0])} is at or below {RELABEL_BASE}, "
                "the ids the joiner gives re-initialised landmarks"
            )
        if not self.aliases or not features.any():
            return submap
        current = self._current
        ids = submap.ids.copy()
        moved = False
        for i in np.flatnonzero(features).tolist():
            landmark = current.get(int(ids[i]))
            if landmark is not None:
                ids[i] = landmark
                moved = True
        return _with_ids(submap, ids) if moved else submap

    def reinitialise(self, result: GateResult, gated: LocalMap) -> GateResult:
        """Turn the split-off sightings of suspect features into new landmarks.

        Args:
            result: the gate's decision on ``gated``.
            gated: the submap the gate tested (:meth:`apply` done).

        Returns:
            ``result`` with those features no longer in ``split``, in ``reinitialised`` instead,
            and a ``submap`` that holds them under their new ids (the other split variables
            still marginalised out). Unchanged when the submap is gated whole or none qualifies.
        """
        if result.rejected or not result.split:
            return result
        suspects = set(self.suspects)
        renew = [v for v in result.split if v.kind == FEATURE and self.front_id(v.var_id) in suspects]
        if not renew:
            return result
        new_ids = {v.var_id: RELABEL_BASE - (len(self.aliases) + k) for k, v in enumerate(renew)}
        ids = gated.ids.copy()
        for i in np.flatnonzero(gated.kinds == FEATURE).tolist():
            ids[i] = new_ids.get(int(ids[i]), int(ids[i]))
        kept = _with_ids(gated, ids)
        still = [v for v in result.split if v.var_id not in new_ids or v.kind != FEATURE]
        drop = [kept.key_set[int(k)] for k in var_keys([v.var_id for v in still], [v.kind for v in still])]
        submap = marginalise_out(kept, drop) if drop else kept
        pairs = tuple((self.front_id(v.var_id), new_ids[v.var_id]) for v in renew)
        return replace(result, split=tuple(still), submap=submap, reinitialised=pairs)

    def after(self, result: GateResult) -> Relabels:
        """Return the relabels once the gate's decision ``result`` is settled (the rest joined, or nothing left to join).

        New landmarks are recorded; a feature split off becomes suspect; a common feature that
        passed, or was re-initialised, is suspect no more. A submap gated whole changes nothing.
        """
        if result.rejected:
            return self
        split = {self.front_id(v.var_id) for v in result.split if v.kind == FEATURE}
        passed = {self.front_id(v.var_id) for v in result.variables if v.kind == FEATURE} - split
        renewed = {front for front, _ in result.reinitialised}
        suspects = (set(self.suspects) - passed - renewed) | (split - renewed)
        if not result.reinitialised and suspects == set(self.suspects):
            return self
        return Relabels((*self.aliases, *result.reinitialised), tuple(sorted(suspects)))


def _with_ids(submap: LocalMap, ids: np.ndarray) -> LocalMap:
    """``submap`` with feature ids changed (same kinds, estimate and information)."""
    out = submap.replace(ids=ids)
    keys = var_keys(ids, submap.kinds)
    seed_key_lookup(out, keys, dict(zip(keys.tolist(), range(keys.size), strict=True)))
    return out


@dataclass(frozen=True)
class Reinitialisation:
    """A feature the gate re-initialised (for report.json's ``reinitialised``, and the node).

    Attributes:
        submap: sequence number of the submap whose sighting started the new landmark.
        robot: the robot whose stream it came in (``""``: the only one).
        feature: the front-end's feature id.
        landmark: the new landmark's id (:data:`RELABEL_BASE` minus a count).
        joined: submaps in the map once that submap was joined (its place in the join order, all robots).
    """

    submap: int
    robot: str
    feature: int
    landmark: int
    joined: int

    def as_dict(self) -> dict[str, int | str]:
        """JSON-ready: ``{"submap", "robot", "feature", "landmark", "joined"}``."""
        return {"submap": self.submap, "robot": self.robot, "feature": self.feature, "landmark": self.landmark,
                "joined": self.joined}


def as_joined(
    maps: Sequence[LocalMap],
    records: Sequence[Reinitialisation],
    joined_at: Sequence[int | None],
    before: Relabels | None = None,
) -> list[LocalMap]:
    """Return the submaps under the feature ids they were joined with (to score a map against them).

    Args:
        maps: the submaps as the front-end sent them.
        records: the re-initialisations (:attr:`~linear_slam_ros.joiner.joiner.Joiner.reinitialised`).
        joined_at: each map's place in the join order (:attr:`Reinitialisation.joined`'s count;
            ``None``: never joined, renamed by every record).
        before: the re-initialisations of a state the joining started from (a snapshot).

    Each map is renamed by ``before`` and the re-initialisations made up to and including its own join.
    """
    base = before.aliases if before is not None else ()
    out = []
    for m, at in zip(maps, joined_at, strict=True):
        aliases = (*base, *((r.feature, r.landmark) for r in records if at is None or r.joined <= at))
        out.append(Relabels(aliases).apply(m) if aliases else m)
    return out
