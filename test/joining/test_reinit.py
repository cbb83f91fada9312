"""Re-initialising a feature whose sightings keep failing the gate (joining/reinit.py), through the joiner."""

from __future__ import annotations

import numpy as np
import pytest

from linear_slam_ros.core.errors import InvalidMapError
from linear_slam_ros.core.geometry import rot2
from linear_slam_ros.core.local_map import FEATURE, LocalMap
from linear_slam_ros.evaluation.synthetic import World, make_world, noisy_local_maps
from linear_slam_ros.joiner.joiner import Joiner, global_result
from linear_slam_ros.joiner.snapshot import decode_state, encode_state
from linear_slam_ros.joiner.strategy import JoinMethod
from linear_slam_ros.joining.gate import GateResult, VariableNis
from linear_slam_ros.joining.reinit import RELABEL_BASE, Reinitialisation, Relabels, as_joined

PROBABILITY = 0.99999999


@pytest.fixture
def world() -> World:
    return make_world(2, 60, 12, np.random.default_rng(5), loops=2.0)  # few features, each seen by many submaps


@pytest.fixture
def maps(world: World) -> list[LocalMap]:
    return noisy_local_maps(world, np.random.default_rng(6), steps_per_map=3, sensor_range=8.0)


def _sightings(maps: list[LocalMap], start: int) -> tuple[int, list[int]]:
    """A feature seen by submaps ``start``, ``start + 1`` and ``start + 2`` (and before): its id and those indices."""
    seen_before = {int(i) for m in maps[:start] for i in m.ids[m.kinds == FEATURE]}
    for f in sorted(seen_before):
        if all(f in m.ids[m.kinds == FEATURE] for m in maps[start:start + 3]):
            return f, [start, start + 1, start + 2]
    raise AssertionError("no feature seen by three consecutive submaps")


def _moved(m: LocalMap, feature: int, shift: float, world: World) -> LocalMap:
    """``m`` with ``feature`` moved by ``shift`` m along the world's x (the front-end's landmark is elsewhere now)."""
    i = int(np.flatnonzero((m.ids == feature) & (m.kinds == FEATURE))[0])
    x = m.x.copy()
    heading = world.poses[m.frame_id][2]
    x[m.scalar_slice(i)] += rot2(np.array(heading)) @ np.array([shift, 0.0])  # the world's x, seen from the frame
    return m.replace(x=x)


def _offer_all(j: Joiner, maps: list[LocalMap]) -> None:
    for seq, m in enumerate(maps, start=1):
        assert j.offer(m, seq) == [seq]


def test_a_feature_that_moved_is_split_off_once_then_re_initialised(maps, world):
    j = Joiner(JoinMethod.ONLINE_DC, gate_probability=PROBABILITY)
    k = 12
    f, later = _sightings(maps, k)
    stream = list(maps)
    for i in range(k, len(stream)):  # from submap k on, every sighting of f is 4 m away from the old one
        if f in stream[i].ids[stream[i].kinds == FEATURE]:
            stream[i] = _moved(stream[i], f, 4.0, world)
    _offer_all(j, stream[: k + 2])
    saved = j.save()  # just after the re-initialisation
    for seq, m in enumerate(stream[k + 2 :], start=k + 3):
        assert j.offer(m, seq) == [seq]
    assert [(g.submap, g.variables) for g in j.gated] == [(k + 1, (f,))]  # only the first moved sighting is kept out
    assert j.reinitialised == [Reinitialisation(k + 2, "", f, RELABEL_BASE, k + 2)]
    assert j.state.relabels.aliases == ((f, RELABEL_BASE),) and j.state.relabels.suspects == ()
    final = global_result(j.state)
    where = [final.index_of(2 * i + FEATURE) for i in (f, RELABEL_BASE)]  # the old landmark and the new one
    assert None not in where
    old, new = (final.x[final.scalar_slice(i)] for i in where)
    assert 3.5 < np.linalg.norm(old - new) < 4.5  # 4 m apart, as in the world
    # saved and restored with the state: a joiner restored from it goes on alike, gate on or off
    assert decode_state(encode_state(saved)).state.relabels == j.state.relabels
    for gate in (PROBABILITY, None):
        other = Joiner(JoinMethod.ONLINE_DC, gate_probability=gate)
        other.restore(decode_state(encode_state(saved)))
        for seq, m in enumerate(stream[k + 2 :], start=k + 3):
            assert other.offer(m, seq) == [seq]
        assert other.gated == [] and other.reinitialised == []
        np.testing.assert_allclose(global_result(other.state).x, final.x, atol=1e-12)


def test_a_re_initialisation_whose_join_fails_is_not_recorded(maps, world, monkeypatch):
    import linear_slam_ros.joiner.joiner as joiner_module
    from linear_slam_ros.core.errors import SolverError

    j = Joiner(JoinMethod.ONLINE_DC, gate_probability=PROBABILITY)
    k = 12
    f, _ = _sightings(maps, k)
    stream = [_moved(m, f, 4.0, world) if i in (k, k + 1) else m for i, m in enumerate(maps)]
    for seq, m in enumerate(stream[: k + 1], start=1):
        j.offer(m, seq)
    assert j.state.relabels.suspects == (f,)
    real = joiner_module.join_step

    def failing(state, submap, seq, robot=""):
        if seq == k + 2:
            raise SolverError("a system the numbers make singular")
        return real(state, submap, seq, robot)

    monkeypatch.setattr(joiner_module, "join_step", failing)
    assert j.offer(stream[k + 1], k + 2) == []
    assert j.reinitialised == [] and j.state.relabels.suspects == (f,) and j.rejected["SolverError"] == 1
    assert len(j.gated) == 1  # the first split, only


def test_one_wrong_sighting_is_split_off_and_the_next_clean_one_clears_the_suspicion(maps, world):
    j = Joiner(JoinMethod.ONLINE_DC, gate_probability=PROBABILITY)
    k = 12
    f, _ = _sightings(maps, k)
    stream = list(maps)
    stream[k] = _moved(stream[k], f, 4.0, world)
    for seq, m in enumerate(stream[: k + 1], start=1):
        j.offer(m, seq)
    assert j.state.relabels.suspects == (f,)
    for seq, m in enumerate(stream[k + 1 :], start=k + 2):
        j.offer(m, seq)
    assert [g.variables for g in j.gated] == [(f,)] and j.reinitialised == []
    assert j.state.relabels == Relabels()  # cleared by the next sighting, which passed


def test_apply_renames_and_refuses_reserved_ids(maps):
    m = maps[3]
    f = int(m.ids[m.kinds == FEATURE][0])
    relabels = Relabels(((f, RELABEL_BASE - 4),))
    renamed = relabels.apply(m)
    assert renamed.index_of(2 * (RELABEL_BASE - 4) + FEATURE) is not None and renamed.index_of(2 * f + FEATURE) is None
    assert renamed.key_set[2 * (RELABEL_BASE - 4) + FEATURE] == int(np.flatnonzero((m.ids == f) & (m.kinds == FEATURE))[0])
    np.testing.assert_array_equal(renamed.x, m.x)
    assert Relabels().apply(m) is m and relabels.front_id(RELABEL_BASE - 4) == f and relabels.front_id(f) == f
    ids = m.ids.copy()
    ids[np.flatnonzero(m.kinds == FEATURE)[0]] = RELABEL_BASE
    with pytest.raises(InvalidMapError, match=rf"feature id {RELABEL_BASE} is at or below {RELABEL_BASE}"):
        Relabels().apply(m.replace(ids=ids))
    j = Joiner(JoinMethod.ONLINE_DC, gate_probability=PROBABILITY)
    assert j.offer(m.replace(ids=ids), 1) == [] and j.rejected["InvalidMapError"] == 1  # refused, counted
    off = Joiner(JoinMethod.ONLINE_DC)  # with the gate off too: turned on later, its first landmark would take that id
    assert off.offer(m.replace(ids=ids), 1) == [] and off.rejected["InvalidMapError"] == 1


def test_a_submap_gated_whole_changes_nothing_and_poses_are_never_re_initialised():
    pose = VariableNis(5, 0, 99.0, 3)
    feature = VariableNis(9, FEATURE, 99.0, 2)
    relabels = Relabels(suspects=(9,))
    whole = GateResult(0.99, 1.0, 5, 2.0, split=(pose, feature), rejected=True, variables=(pose, feature))
    assert relabels.after(whole) is relabels and relabels.reinitialise(whole, None) is whole  # type: ignore[arg-type]
    split_pose = GateResult(0.99, 1.0, 5, 2.0, split=(pose,), variables=(pose, feature))
    assert relabels.reinitialise(split_pose, None) is split_pose  # type: ignore[arg-type]
    assert relabels.after(split_pose) == Relabels()  # feature 9 passed: cleared; a pose split off is no suspect
    assert Relabels().after(split_pose) == Relabels()


def test_as_joined_renames_each_submap_by_the_re_initialisations_up_to_its_own(maps):
    f = int(maps[5].ids[maps[5].kinds == FEATURE][0])
    record = Reinitialisation(submap=4, robot="", feature=f, landmark=RELABEL_BASE, joined=4)
    assert record.as_dict() == {"submap": 4, "robot": "", "feature": f, "landmark": RELABEL_BASE, "joined": 4}
    seen = as_joined(maps[:6], [record], [1, 2, 3, 4, 5, None])
    for at, (raw, got) in enumerate(zip(maps[:6], seen, strict=True), start=1):
        has_f = bool(np.any((raw.ids == f) & (raw.kinds == FEATURE)))
        renamed = got.index_of(2 * RELABEL_BASE + FEATURE) is not None
        assert renamed == (has_f and at >= 4) and (at >= 4 or got is raw)
    # what a snapshot the joining started from had re-initialised renames every map
    start = as_joined(maps[:2], [], [1, 2], Relabels(((f, RELABEL_BASE - 7),)))
    assert all(m.index_of(2 * f + FEATURE) is None for m in start)
