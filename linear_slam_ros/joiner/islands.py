"""Chains and islands of the joiner state: a gap or a second robot never ends the map.

Submaps of one robot normally each start where the previous one ended (their frame pose is the
previous end pose, or they hold it): they form a *chain*, one strategy state (an online D&C
stack, a sequential map). A submap that continues no chain — a submap was lost before it, the
node restarted, or it is another robot's — starts a new chain instead of being rejected.

Chains that share enough to fix their relative frame (a pose, or 2 features in 2D / 3 not
collinear in 3D: :func:`~linear_slam_ros.joining.islands.find_link`) belong to one *island*;
the joined map of an island is its chains' results joined through those links, in closed form
(:func:`~linear_slam_ros.joining.islands.merge_maps`). Links are found as submaps arrive (the
new submap's variables against the other islands': :func:`link_islands`); an island's chains are
joined when its map is asked for (:func:`island_result`), and pairs of similar size that no
longer grow are joined into one chain (:func:`collapse_frozen`).

The *main island* is the one holding the first chain (the first submap joined, whose frame pose
is ``map_frame``'s); ``global_map`` carries it. An island's label is the index of its first
chain (a new island's is its chain's index; linked islands take the smaller; when chains are
joined and renumbered, the labels follow: :func:`collapse_frozen`), so the main island's label is 0
and no two islands share one.
"""

from __future__ import annotations

import collections
import contextlib
import logging
import threading
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from linear_slam_ros.core.errors import FrameError
from linear_slam_ros.core.frames import change_frame
from linear_slam_ros.core.local_map import LocalMap
from linear_slam_ros.joining.islands import Link, find_link, merge_maps

logger = logging.getLogger(__name__)

FloatArray = npt.NDArray[np.float64]

MAIN_ISLAND = 0
"""Label of the main island (the one holding the first chain)."""


@dataclass(frozen=True)
class Chain:
    """Submaps of one robot that each start where the previous one ended: one strategy state.

    Attributes:
        joined: the strategy's state of these submaps.
        robot: the robot (stream) whose submaps these are (``""``: the single robot).
        first_pose_id: frame pose of its first submap.
        end_id: end pose of its newest submap (``None`` when that submap did not say).
        n_joined: submaps joined into it.
        island: label of its island (the index of the island's first chain).
        stamp: the joiner's submap count when it was last extended (the newest chain has the largest).
    """

    joined: Any
    robot: str
    first_pose_id: int
    end_id: int | None
    n_joined: int
    island: int
    stamp: int

    def continued_by(self, submap: LocalMap) -> bool:
        """Whether ``submap`` starts where this chain ends (it is in, or holds, the end pose)."""
        return self.end_id is None or submap.frame_id == self.end_id or submap.has_pose(self.end_id)


@dataclass(frozen=True)
class Stream:
    """Sequence position of one robot's stream of submaps.

    Attributes:
        robot: the robot (``""``: the single robot).
        next_seq: sequence number expected next (``None`` before its first submap).
        last_seq: sequence number of its last joined submap.
        chain: index of the chain its newest submap joined (-1: none yet).
    """

    robot: str = ""
    next_seq: int | None = None
    last_seq: int | None = None
    chain: int = -1


@dataclass(frozen=True)
class IslandSummary:
    """One island, for reports and statistics.

    Attributes:
        label: its label (:data:`MAIN_ISLAND` for the main island).
        n_submaps: submaps joined into it.
        chains: indices of its chains.
    """

    label: int
    n_submaps: int
    chains: tuple[int, ...]


def summarize(chains: Sequence[Chain]) -> list[IslandSummary]:
    """Return the islands of ``chains``: the main island first, then the others by size (largest first)."""
    members: dict[int, list[int]] = collections.defaultdict(list)
    for i, c in enumerate(chains):
        members[c.island].append(i)
    out = [IslandSummary(label, sum(chains[i].n_joined for i in idx), tuple(idx)) for label, idx in members.items()]
    out.sort(key=lambda s: (s.label != MAIN_ISLAND, -s.n_submaps, s.label))
    return out


class IslandCache:
    """Results and key sets of chains and islands, computed once per state value (a cache only).

    Everything here is a function of immutable state values, so the cache never changes a
    result, only when it is computed. Entries are held by the identity of the strategy state (and
    a reference to it, so the identity is not reused); the least recently used go beyond
    ``results`` joined maps (large) and ``keys`` key sets (small: every frozen chain's stays, so
    links are looked for without joining anything again). Thread-safe: the node asks for results
    from its output thread while the arrival thread joins.
    """

    def __init__(self, results: int = 8, keys: int = 4096) -> None:
        self._results: collections.OrderedDict[Any, tuple[Any, Any]] = collections.OrderedDict()
        self._keys: collections.OrderedDict[Any, tuple[Any, Any]] = collections.OrderedDict()
        self._sizes = {id(self._results): results, id(self._keys): keys}
        self._lock = threading.Lock()
        self.anchors: dict[int, FloatArray] = {}
        """Pose (map frame) of each main-island chain's first pose in the last joined main map."""

    def _get(self, table: collections.OrderedDict[Any, tuple[Any, Any]], key: Any, owner: Any, make: Callable[[], Any]) -> Any:
        with self._lock:
            hit = table.get(key)
            if hit is not None and _same(hit[0], owner):
                table.move_to_end(key)
                return hit[1]
        value = make()
        with self._lock:
            table[key] = (owner, value)
            while len(table) > self._sizes[id(table)]:
                table.popitem(last=False)
        return value

    def result(self, result_of: Callable[[Any], LocalMap | None], chain: Chain) -> LocalMap:
        """Return the joined map of one chain (in its newest end pose's frame)."""
        joined = chain.joined

        def make() -> LocalMap:
            out = result_of(joined)
            assert out is not None  # a chain holds at least one submap
            return out

        return self._get(self._results, id(joined), joined, make)

    def keys(self, result_of: Callable[[Any], LocalMap | None], chain: Chain) -> frozenset[int]:
        """Return the variable keys of one chain (its frame pose's included)."""
        joined = chain.joined

        def make() -> frozenset[int]:
            result = self.result(result_of, chain)
            return frozenset(result.keys.tolist()) | {2 * result.frame_id}

        return self._get(self._keys, id(joined), joined, make)

    def pair(self, members: tuple[Any, Any], make: Callable[[], LocalMap | None]) -> LocalMap | None:
        """Return the join of two chains ``members`` (their strategy states), ``None`` when they do not link.

        A pair that does not link is remembered among the small entries; a join is not (it is used at once).
        """
        key = ("pair", *(id(m) for m in members))
        with self._lock:
            hit = self._keys.get(key)
            if hit is not None and _same(hit[0], members):
                return None
        joined = make()
        if joined is None:
            self._get(self._keys, key, members, lambda: None)
        return joined

    def island(self, what: str, members: tuple[Any, ...], make: Callable[[], Any]) -> Any:
        """Return ``what`` (a label of the computation) of the chains ``members`` (their strategy states)."""
        return self._get(self._results, (what, *(id(m) for m in members)), members, make)


def _same(a: Any, b: Any) -> bool:
    """Whether two owners of cache entries are the same objects (tuples: element by element)."""
    if isinstance(a, tuple) and isinstance(b, tuple):
        return len(a) == len(b) and all(x is y for x, y in zip(a, b, strict=True))
    return a is b


def route(chains: Sequence[Chain], submap: LocalMap, robot: str, current: int, strict: bool = True) -> list[int]:
    """Return the chains ``submap`` may continue, most likely first.

    The robot's current chain first, then the others from the newest. ``strict``: only those it
    starts where they end (:meth:`Chain.continued_by`); else those, then every other chain (a
    strategy may accept a submap in the frame of an earlier pose: sequential joining does).
    """
    order = sorted(range(len(chains)), key=lambda i: (i != current, chains[i].robot != robot, -chains[i].stamp))
    continued = [i for i in order if chains[i].continued_by(submap)]
    return continued if strict else continued + [i for i in order if i not in continued]


def link_islands(
    chains: list[Chain], target: int, submap: LocalMap, result_of: Callable[[Any], LocalMap | None], cache: IslandCache,
    holds: Callable[[Any, list[int]], bool | None] | None = None,
) -> list[Chain]:
    """Relabel islands that ``submap`` (just joined into chain ``target``) connects to ``target``'s island.

    Another island is linked when the submap shares a variable with one of its chains and the two
    chains share enough to fix their relative frame (:func:`find_link`), or failing that the two
    islands' maps do (common features spread over several chains count). Linked islands take the
    smaller label. Nothing is joined into the state here (see :func:`collapse_frozen`).

    Whether a chain shares a variable with the submap is asked of ``holds`` (whether a strategy
    state holds any of some keys, cheaply: no join; ``None``: it cannot tell), else of the chain's
    joined map: another robot's chain changes at each of its arrivals, and forming its map for
    every arrival of this one cost hundreds of milliseconds an arrival at 300 submaps each.

    Returns:
        The chains with their new labels (the same list when nothing changed).
    """
    labels = {c.island for c in chains}
    if len(labels) == 1:
        return chains
    mine = chains[target].island
    keys = submap.keys.tolist() + [2 * submap.frame_id]
    linked = False

    def shares(chain: Chain) -> bool:
        if chain.end_id is not None and 2 * chain.end_id in keys:  # its newest frame (a result's frame is no variable)
            return True
        answer = holds(chain.joined, keys) if holds is not None else None
        if answer is not None:
            return answer
        known = cache.keys(result_of, chain)
        return any(k in known for k in keys)

    for label in sorted(labels - {mine}):
        touched = [c for c in chains if c.island == label and shares(c)]
        if not touched:
            continue
        ours = cache.result(result_of, chains[target])
        link = next((lk for c in touched if (lk := find_link(cache.result(result_of, c), ours)) is not None), None)
        if link is None:  # through the islands' unions
            theirs, whole = island_result(chains, label, result_of, cache), island_result(chains, mine, result_of, cache)
            link = find_link(theirs, whole) if theirs is not None and whole is not None else None
        if link is None:
            continue
        logger.info(
            "submap %r links island %d (chain %d) with island %d through %s: they are one island now",
            submap.name, mine, target, label, link.describe(),
        )
        chains, mine = _merge_islands(chains, mine, label)
        linked = True
    return _link_grown(chains, mine, result_of, cache) if linked else chains


def _merge_islands(chains: list[Chain], mine: int, label: int) -> tuple[list[Chain], int]:
    """Relabel islands ``mine`` and ``label`` as one, under the smaller label; return the chains and that label."""
    new, old = min(mine, label), max(mine, label)
    return [c if c.island != old else _relabel(c, new) for c in chains], new


def _link_grown(chains: list[Chain], mine: int, result_of: Callable[[Any], LocalMap | None], cache: IslandCache) -> list[Chain]:
    """Link the other islands that island ``mine``, just grown by a link, now shares enough with.

    Each was tested against ``mine`` before it grew, if at all: a third robot's island that
    bridges two others (it shares a feature with each) joins one of them, and the grown island
    then shares enough with the other, which no submap may touch again. Tested through the islands'
    unions, only for an island whose chains share a variable with ``mine``'s (their key sets,
    cached), until nothing changes.
    """
    while True:
        grown = frozenset().union(*(cache.keys(result_of, c) for c in chains if c.island == mine))
        for label in sorted({c.island for c in chains} - {mine}):
            if not any(grown & cache.keys(result_of, c) for c in chains if c.island == label):
                continue
            theirs, whole = island_result(chains, label, result_of, cache), island_result(chains, mine, result_of, cache)
            link = find_link(theirs, whole) if theirs is not None and whole is not None else None
            if link is None:
                continue
            logger.info("island %d, grown, links island %d through %s: they are one island now", mine, label, link.describe())
            chains, mine = _merge_islands(chains, mine, label)
            break
        else:
            return chains


def collapse_frozen(
    chains: list[Chain], active: set[int], seed: Callable[[LocalMap, int], Any], result_of: Callable[[Any], LocalMap | None],
    cache: IslandCache,
) -> tuple[list[Chain], list[int]]:
    """Join pairs of an island's chains that no longer grow into one chain (its strategy state seeded from their map).

    A chain grows while it holds some robot's newest submap (``active``). Two others of one island
    are joined when they link (:func:`find_link`, closed form) and are of similar size (at most
    twice as many submaps), as the levels of divide and conquer are: every change of frame couples
    the moved map's old origin with all its variables, so joining each new part into one growing
    map (as sequential joining does) would fill the information in; pairs of similar size keep
    it sparse, and an island keeps about log2(gaps) frozen chains. The joined chain takes the
    lower index.

    Returns:
        The chains, and where each old index went (``-1``: joined into another).
    """
    out: list[Chain | None] = list(chains)
    changed = False
    while True:
        pair = _similar_linked_pair(out, active, result_of, cache)
        if pair is None:
            break
        (i, a), (k, b), joined = pair
        newest = a if a.stamp >= b.stamp else b
        if newest.end_id is not None and newest.end_id != joined.frame_id:  # its end is the newest part's
            with contextlib.suppress(FrameError):
                joined = change_frame(joined.replace(end_id=newest.end_id), newest.end_id)
        n = a.n_joined + b.n_joined
        out[i] = Chain(seed(joined, n), a.robot, a.first_pose_id, newest.end_id, n, a.island, newest.stamp)
        out[k] = None
        changed = True
        logger.debug("island %d: chains %d and %d, which no longer grow, joined into one (%d submaps)", a.island, i, k, n)
    if not changed:
        return chains, list(range(len(chains)))
    kept = [i for i, c in enumerate(out) if c is not None]
    index = {old: new for new, old in enumerate(kept)}
    return _first_chain_labels([c for c in out if c is not None]), [index.get(i, -1) for i in range(len(chains))]


def _first_chain_labels(chains: list[Chain]) -> list[Chain]:
    """Relabel each island with the index of its first chain (after chains were joined and renumbered).

    A new island's label is the index of its chain, the number of chains before it
    (:func:`~linear_slam_ros.joiner.joiner.join_step`): that label must not be held by another
    island, so an island's label never exceeds its chains' indices. Joining two chains removes
    one and shifts the later ones down; without relabelling, an island whose chains all moved
    down would keep a label the next new island takes too, and the two would count as linked.
    The main island keeps label 0 (chain 0 is never the one removed).
    """
    first: dict[int, int] = {}
    for i, c in enumerate(chains):
        first.setdefault(c.island, i)
    if all(label == i for label, i in first.items()):
        return chains
    return [c if first[c.island] == c.island else _relabel(c, first[c.island]) for c in chains]


def _similar_linked_pair(
    chains: Sequence[Chain | None], active: set[int], result_of: Callable[[Any], LocalMap | None], cache: IslandCache
) -> tuple[tuple[int, Chain], tuple[int, Chain], LocalMap] | None:
    """Return two frozen chains of one island, of similar size, that link, with their joined map (lower index first)."""
    frozen = [(i, c) for i, c in enumerate(chains) if c is not None and i not in active]
    for x, (i, a) in enumerate(frozen):
        for k, b in frozen[x + 1 :]:
            if a.island != b.island or max(a.n_joined, b.n_joined) > 2 * min(a.n_joined, b.n_joined):
                continue

            def join(a: Chain = a, b: Chain = b) -> LocalMap | None:  # memoised: a pair that does not link is tried once
                ra, rb = cache.result(result_of, a), cache.result(result_of, b)
                link = find_link(ra, rb)
                return merge_maps(ra, rb, link, None) if link is not None else None

            joined = cache.pair((a.joined, b.joined), join)
            if joined is not None:
                return (i, a), (k, b), joined
    return None


def _relabel(chain: Chain, label: int) -> Chain:
    return Chain(chain.joined, chain.robot, chain.first_pose_id, chain.end_id, chain.n_joined, label, chain.stamp)


def island_result(
    chains: Sequence[Chain], label: int, result_of: Callable[[Any], LocalMap | None], cache: IslandCache
) -> LocalMap | None:
    """Return the joined map of island ``label``, in the frame of its newest end pose.

    One chain: its result. Several: the chains that no longer grow are joined first (the first
    chain's result, then each other chain as soon as it links with what is joined so far; chains
    that link only with each other are joined with each other first: :func:`join_linked`), and
    that part is cached; then the newest chain, then what links only through it. So while one
    robot extends an island, each output costs one join more than without islands. A chain that
    links with no other part is left out, with a warning (the links found on arrival make this
    rare: a union of chains that only the nonlinear problem would fix, e.g. three pairwise sharing
    one feature each in 2D).
    """
    members = [c for c in chains if c.island == label]
    if not members:
        return None
    if len(members) == 1:
        return cache.result(result_of, members[0])
    newest = max(members, key=lambda c: c.stamp)
    frozen = [c for c in members if c is not newest]

    def join_frozen() -> list[tuple[tuple[Chain, ...], LocalMap]]:
        return join_linked([((c,), cache.result(result_of, c) if i == 0 else result_of(c.joined)) for i, c in enumerate(frozen)])

    def make() -> LocalMap:
        parts = cache.island("frozen", tuple(c.joined for c in frozen), join_frozen)
        joined_parts = join_linked([parts[0], ((newest,), cache.result(result_of, newest)), *parts[1:]])
        joined = joined_parts[0][1]
        rest = [c for group, _ in joined_parts[1:] for c in group]
        if rest:
            logger.warning(
                "island %d: %d chain(s) (first poses %s) link with no other part and are left out of its map",
                label,
                len(rest),
                [c.first_pose_id for c in rest],
            )
        end = newest.end_id
        if end is not None and end != joined.frame_id:
            with contextlib.suppress(FrameError):  # the newest chain was left out: keep the joined map's own end
                joined = change_frame(joined.replace(end_id=end), end)
        return joined

    return cache.island("island", tuple(c.joined for c in members), make)


def join_linked(parts: Sequence[tuple[tuple[Chain, ...], LocalMap | None]]) -> list[tuple[tuple[Chain, ...], LocalMap]]:
    """Join maps into the first, each as soon as it links; parts that link only with each other are joined first.

    Each join is closed form (:func:`~linear_slam_ros.joining.islands.find_link`,
    :func:`~linear_slam_ros.joining.islands.merge_maps`): a common pose, else the frame of common
    features. The first map grows: the earliest other map that links with it is joined into it,
    again and again. When none does, two of the others that link with each other are joined (the
    pair sharing the most variables; ties: the earlier), since their union may link where neither
    does alone (common features spread over several chains); then the first map grows again.
    Links between the others are found once per pair.

    Args:
        parts: ``(chains, map)``: each map with the chains it joins (a map of ``None`` is dropped).

    Returns:
        The parts that remain: the grown first one (its map holds everything that links with it),
        then the others in their order in ``parts``, each with the chains it joins.
    """
    alive: dict[int, tuple[tuple[Chain, ...], LocalMap]] = {i: (g, m) for i, (g, m) in enumerate(parts) if m is not None}
    if not alive:
        return []
    first = min(alive)
    pair_links: dict[tuple[int, int], Link | None] = {}

    def merge(i: int, k: int, link: Link) -> None:
        (group_i, map_i), (group_k, map_k) = alive.pop(i), alive.pop(k)
        alive[i] = (group_i + group_k, merge_maps(map_i, map_k, link, None))
        for pair in [pair for pair in pair_links if i in pair or k in pair]:
            del pair_links[pair]

    while len(alive) > 1:
        grow = next(((k, lk) for k in sorted(alive) if k != first and (lk := find_link(alive[first][1], alive[k][1]))), None)
        if grow is not None:
            merge(first, *grow)
            continue
        others = sorted(k for k in alive if k != first)
        for x, i in enumerate(others):
            for k in others[x + 1 :]:
                if (i, k) not in pair_links:
                    pair_links[(i, k)] = find_link(alive[i][1], alive[k][1])
        linked = [(pair, lk) for pair, lk in pair_links.items() if lk is not None]
        if not linked:
            break
        (i, k), link = min(linked, key=lambda e: (-e[1].n_common, e[0]))
        merge(i, k, link)
    return [alive[i] for i in sorted(alive)]
