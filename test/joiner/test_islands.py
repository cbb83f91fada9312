"""Islands and several robots in the joiner: a gap never ends the map."""

from __future__ import annotations

import logging
import re

import numpy as np
import pytest

from linear_slam_ros.core.errors import ConfigError
from linear_slam_ros.core.frames import change_frame
from linear_slam_ros.core.local_map import FEATURE
from linear_slam_ros.evaluation.runner import run_join
from linear_slam_ros.evaluation.synthetic import exact_local_maps, make_world, noisy_local_maps
from linear_slam_ros.joiner.islands import join_linked
from linear_slam_ros.joiner.joiner import Joiner, current_pose, global_result, island_map
from linear_slam_ros.joiner.robots import ROBOT_ID_STRIDE, global_pose_id, qualify, robot_slots
from linear_slam_ros.joiner.snapshot import read_snapshot, write_snapshot
from linear_slam_ros.joiner.strategy import JoinMethod, MapType
from linear_slam_ros.joining.islands import find_link, poses_of


@pytest.fixture(scope="module")
def maps():
    world = make_world(2, 36, 40, np.random.default_rng(21))
    return noisy_local_maps(world, np.random.default_rng(22), steps_per_map=3)


def _sizes(j: Joiner) -> list[tuple[int, int]]:
    return [(s.label, s.n_submaps) for s in j.state.islands]


@pytest.mark.parametrize("mode", [JoinMethod.ONLINE_DC, JoinMethod.SEQUENTIAL])
def test_a_lost_submap_starts_an_island_that_links_back_through_features(mode, maps, caplog):
    caplog.set_level(logging.INFO, logger="linear_slam_ros.joiner")
    j = Joiner(mode)
    for seq, m in enumerate(maps, start=1):
        if seq != 4:  # seq 4 is lost
            j.offer(m, seq)
    assert j.flush() == list(range(5, len(maps) + 1))  # the stream has ended: seq 4 never comes
    assert j.rejected == {"gap": 1} and j.state.n_joined == len(maps) - 1
    assert "starts island 1" in caplog.text and "links island 1 (chain 1) with island 0" in caplog.text
    assert _sizes(j) == [(0, len(maps) - 1)] and len(j.state.chains) == 2
    joined = global_result(j.state)
    full = run_join(maps, mode).result
    assert joined.frame_id == full.frame_id  # the newest end pose's frame, as without islands
    assert set(joined.feature_ids.tolist()) == set(full.feature_ids.tolist())
    lost = set(maps[3].pose_ids.tolist()) - {maps[3].end_id}  # only the lost submap held them
    assert set(poses_of(joined).tolist()) == set(poses_of(full).tolist()) - lost


def test_without_a_gap_a_submap_that_continues_nothing_is_rejected(maps):
    j = Joiner(JoinMethod.ONLINE_DC)
    reasons = []
    j.on_reject = lambda reason, message: reasons.append((reason, message))
    j.offer(maps[0], 1)
    assert j.offer(maps[3], 2) == []
    assert reasons[0][0] == "FrameError"
    assert "follows seq 1 without a gap" in reasons[0][1] and len(j.state.chains) == 1
    assert j.offer(maps[1], 2) == [2]  # its number stays open for the valid submap


def test_an_island_that_never_links_stays_apart_and_is_said(maps):
    other_world = make_world(2, 12, 10, np.random.default_rng(99))
    stranger = [m.replace(ids=np.where(m.kinds == FEATURE, m.ids + 1000, m.ids + 500), frame_id=m.frame_id + 500,
                          end_id=m.end_id + 500) for m in exact_local_maps(other_world, np.random.default_rng(3), 3)]
    j = Joiner(JoinMethod.ONLINE_DC)
    for seq, m in enumerate(maps[:4], start=1):
        j.offer(m, seq)
    assert current_pose(j.state) is not None
    for seq, m in enumerate(stranger, start=10):  # after a gap: a robot somewhere else, nothing in common
        j.offer(m, seq)
    j.flush()
    assert _sizes(j) == [(0, 4), (1, len(stranger))]
    main = global_result(j.state)
    assert main.n_vars == run_join(maps[:4], JoinMethod.ONLINE_DC).result.n_vars  # the main island only
    other = island_map(j.state, 1)
    assert other is not None and set(other.feature_ids.tolist()) <= set(range(1001, 1100))
    assert current_pose(j.state) is None  # the robot is in island 1: no pose in map_frame
    assert island_map(j.state, 7) is None
    assert j.stats()["n_islands"] == 2.0


def test_feature_only_maps_do_not_start_islands(maps):
    j = Joiner(JoinMethod.ONLINE_DC, MapType.FEATURE_ONLY)
    reasons = []
    j.on_reject = lambda reason, message: reasons.append(message)
    for seq, m in enumerate(maps[:3], start=1):
        j.offer(m, seq)
    far = maps[5].replace(ids=np.where(maps[5].kinds == FEATURE, maps[5].ids + 1000, maps[5].ids))
    j.offer(far, 5)
    j.flush()
    assert reasons[-1].endswith("the maps share no frame; 'feature-only' 'online-dc' maps cannot start islands")
    assert len(j.state.chains) == 1 and j.state.n_joined == 3


def test_islands_and_robot_streams_survive_a_snapshot(maps, tmp_path):
    j = Joiner(JoinMethod.ONLINE_DC)
    for seq, m in enumerate(maps[:8], start=1):
        if seq != 3:
            j.offer(m, seq, "")
    j.flush()
    j.offer(qualify(maps[0], 1), 1, "b")
    j.offer(qualify(maps[2], 1), 3, "b")  # waits for b's 2
    path = tmp_path / "state.npz"
    write_snapshot(path, j.save())
    other = Joiner(JoinMethod.ONLINE_DC)
    other.restore(read_snapshot(path))
    def chains(joiner: Joiner) -> list[tuple[object, ...]]:
        return [(c.robot, c.first_pose_id, c.end_id, c.n_joined, c.island, c.stamp) for c in joiner.state.chains]

    assert chains(other) == chains(j) and len(chains(j)) == 3  # robot a's two chains (one island), robot b's
    assert [(s.robot, s.next_seq, s.last_seq, s.chain) for s in other.state.streams] == [
        (s.robot, s.next_seq, s.last_seq, s.chain) for s in j.state.streams]
    assert other.already_handled(3, "b") and not other.already_handled(2, "b")
    assert other.offer(qualify(maps[1], 1), 2, "b") == [2, 3]
    assert j.offer(qualify(maps[1], 1), 2, "b") == [2, 3]
    np.testing.assert_array_equal(global_result(other.state).x, global_result(j.state).x)


def test_two_robots_keep_their_sequence_numbers_and_pose_ids_apart(maps):
    half = len(maps) // 2
    j = Joiner(JoinMethod.ONLINE_DC)
    for k in range(half):  # both robots publish seq 1, 2, ... concurrently
        j.offer(maps[k], k + 1, "a")
        if half + k < len(maps):
            j.offer(qualify(maps[half + k], 1), k + 1, "b")
    assert j.n_skipped == 0 and j.n_rejected == 0
    assert _sizes(j) == [(0, len(maps))]  # robot b's island met robot a's through common features
    joined = global_result(j.state, "first_pose")
    full = run_join(maps, JoinMethod.ONLINE_DC).result
    b_poses = [int(p) for p in joined.pose_ids if p >= ROBOT_ID_STRIDE]
    assert b_poses and min(b_poses) == global_pose_id(1, maps[half].frame_id)
    assert set(joined.feature_ids.tolist()) == set(full.feature_ids.tolist())
    assert [s.robot for s in j.state.streams] == ["a", "b"]


def test_robot_ids_are_global_and_names_checked(maps):
    m = maps[3]
    q = qualify(m, 2)
    assert q.frame_id == 2 * ROBOT_ID_STRIDE + m.frame_id and q.end_id == 2 * ROBOT_ID_STRIDE + m.end_id
    np.testing.assert_array_equal(q.feature_ids, m.feature_ids)  # features are shared
    assert qualify(m, 0) is m
    assert global_pose_id(1, ROBOT_ID_STRIDE * 3 + 4) == ROBOT_ID_STRIDE * 3 + 4  # another robot's pose, named globally
    assert robot_slots(["a", "b_2"]) == {"a": 0, "b_2": 1}
    with pytest.raises(ConfigError, match="robots lists 'a' twice"):
        robot_slots(["a", "a"])
    with pytest.raises(ConfigError, match=r"robots\[1\]='2x' is not a robot namespace"):
        robot_slots(["a", "2x"])
    with pytest.raises(ConfigError, match=r"robots\[0\]='' is not"):
        robot_slots([""])
    with pytest.raises(ConfigError, match="robot slot -1 must be >= 0"):
        qualify(m, -1)


def test_a_robot_pose_named_both_by_its_own_and_its_global_id_is_refused():
    """Robot 1's pose 3 sent as 3 and as 2^32 + 3 would be one variable twice once qualified."""
    from linear_slam_ros.core.errors import InvalidMapError
    from linear_slam_ros.core.local_map import POSE, LocalMap

    s = ROBOT_ID_STRIDE

    def star(frame: int, ids: list[int]) -> LocalMap:
        n = len(ids)
        return LocalMap(2, frame, ids[-1], np.array(ids), np.full(n, POSE), np.arange(3.0 * n), np.eye(3 * n))

    with pytest.raises(InvalidMapError, match=r"robot slot 1: pose 3 is given twice, by its own id 3 and by its global id "
                                              r"4294967299$"):
        qualify(star(2, [3, s + 3]), 1)
    with pytest.raises(InvalidMapError, match=r"pose 3 is given twice, .* global id 4294967299 \(frame pose and variable\)"):
        qualify(star(3, [s + 3, 4]), 1)
    assert qualify(star(2, [3, 2 * s + 3]), 1).pose_ids.tolist() == [s + 3, 2 * s + 3]  # robot 2's pose 3: another pose
    assert qualify(star(2, [3, s + 3]), 0).pose_ids.tolist() == [3, s + 3]  # robot 0's ids are not rewritten


def test_a_submap_of_the_other_dimension_never_starts_an_island(maps):
    other = noisy_local_maps(make_world(3, 9, 10, np.random.default_rng(5)), np.random.default_rng(6), steps_per_map=3)
    j = Joiner(JoinMethod.ONLINE_DC)
    reasons = []
    j.on_reject = lambda reason, message: reasons.append((reason, message))
    j.offer(maps[0], 1)
    j.offer(other[1], 3)  # after a gap, but 3D in a 2D map
    assert j.flush() == []  # the stream has ended: the gap is skipped, the 3D submap rejected and dropped
    assert [r for r, _ in reasons] == ["gap", "InvalidMapError"]
    assert "is 3D, the global map is 2D" in reasons[1][1] and len(j.state.chains) == 1 and not j.already_handled(4)


def test_a_node_restarted_without_its_state_says_what_its_map_holds(maps):
    now = [0.0]
    j = Joiner(JoinMethod.ONLINE_DC, reorder_timeout=1.0, clock=lambda: now[0])
    reasons = []
    j.on_reject = lambda reason, message: reasons.append(message)
    rest = list(enumerate(maps, start=1))[5:]  # the node restarted after seq 5: it is fed the rest
    for seq, m in rest:
        assert j.offer(m, seq) == []  # waits: seq 1 is expected
    now[0] = 1.5
    assert j.expire() == [("", seq) for seq, _ in rest]
    assert reasons == ["submaps seq 1..5 never arrived or were rejected (no progress for 1.5 s): skipped"]
    assert _sizes(j) == [(0, len(rest))] and j.state.first_pose_id == maps[5].frame_id  # its map starts at seq 6
    assert j.stats()["n_joined"] == len(rest)


def test_sequential_still_joins_a_submap_in_the_frame_of_an_earlier_pose(maps):
    j = Joiner(JoinMethod.SEQUENTIAL)
    for seq, m in enumerate(maps[:3], start=1):
        j.offer(m, seq)
    interior = int(maps[1].pose_ids[0])  # in the map, but not its end
    again = change_frame(maps[1], interior).replace(name="again", end_id=interior)  # maps[1] seen from there
    assert not j.state.chains[0].continued_by(again)
    assert j.offer(again, 4) == [4] and len(j.state.chains) == 1  # the strategy takes it: no island


@pytest.mark.parametrize("mode", [JoinMethod.ONLINE_DC, JoinMethod.SEQUENTIAL])
def test_chains_that_no_longer_grow_are_joined_into_one_and_the_map_stays_exact(mode):
    """Noise-free maps (Lemma 1's setting): however the islands are joined, the map is the truth."""
    world = make_world(2, 30, 40, np.random.default_rng(41))
    maps = exact_local_maps(world, np.random.default_rng(42), poses_per_map=2, sensor_range=8.0)
    j = Joiner(mode)
    for seq, m in enumerate(maps, start=1):
        if seq not in (4, 9):  # two submaps lost: three chains, the first two no longer grow
            j.offer(m, seq)
    j.flush()
    assert _sizes(j) == [(0, len(maps) - 2)]
    assert len(j.state.chains) == 2 and j.state.stream().chain == 1  # chains 0 and 1 joined into one
    joined = global_result(j.state, "first_pose")
    truth = run_join(maps, JoinMethod.ONLINE_DC).result  # exact: every map is the truth in its frame
    truth = change_frame(truth, joined.frame_id)
    for i in range(joined.n_vars):
        k = int(joined.keys[i])
        if truth.index_of(k) is None:
            continue
        diff = joined.x[joined.scalar_slice(i)] - truth.x[truth.scalar_slice(truth.index_of(k))]
        np.testing.assert_allclose(np.r_[diff[:2], np.sin(diff[2:])], 0.0, atol=1e-8)


def test_after_a_gap_the_fresh_pose_continues_from_where_the_last_map_put_the_chain():
    """Noise-free maps: the composed pose equals the joined map's end pose exactly."""
    world = make_world(2, 30, 40, np.random.default_rng(51))
    maps = exact_local_maps(world, np.random.default_rng(52), poses_per_map=2, sensor_range=8.0)
    j = Joiner(JoinMethod.ONLINE_DC)
    for seq, m in enumerate(maps[:8], start=1):
        if seq != 4:
            j.offer(m, seq)
    j.flush()
    assert j.state.stream().chain == 1 and _sizes(j) == [(0, 7)]
    assert current_pose(j.state) is None  # no joined map has placed the new chain yet
    global_result(j.state)  # an output: the main island's map places chain 1's first pose
    for seq in range(9, 12):
        j.offer(maps[seq - 1], seq)
        end_id, pose = current_pose(j.state)
        truth = global_result(j.state, "first_pose")
        assert end_id == maps[seq - 1].end_id
        diff = pose - truth.pose(end_id)
        np.testing.assert_allclose(np.r_[diff[:2], np.sin(diff[2])], 0.0, atol=1e-9)


def _assert_exact(joined, truth) -> None:
    """Every variable of ``joined`` that ``truth`` holds equals it (angles modulo 2 pi)."""
    truth = change_frame(truth, joined.frame_id)
    compared = 0
    for i in range(joined.n_vars):
        k = truth.index_of(int(joined.keys[i]))
        if k is None:
            continue
        diff = joined.x[joined.scalar_slice(i)] - truth.x[truth.scalar_slice(k)]
        np.testing.assert_allclose(np.r_[diff[:2], np.sin(diff[2:])], 0.0, atol=1e-8)
        compared += 1
    assert compared > 0


def test_a_new_island_never_takes_the_label_of_one_that_stays_apart():
    """Joining two frozen chains renumbers the later ones: the labels follow, so a new island's is fresh.

    Without that, the stranger (label 2) and the chain started after it (index 2, so label 2) shared a
    label: when the new chain linked with the main island, the stranger was counted in it too.
    """
    world = make_world(2, 30, 40, np.random.default_rng(41))
    maps = exact_local_maps(world, np.random.default_rng(42), poses_per_map=2, sensor_range=8.0)
    other_world = make_world(2, 12, 10, np.random.default_rng(99))
    stranger = [m.replace(ids=np.where(m.kinds == FEATURE, m.ids + 1000, m.ids + 500), frame_id=m.frame_id + 500,
                          end_id=m.end_id + 500) for m in exact_local_maps(other_world, np.random.default_rng(3), 3)[:2]]
    j = Joiner(JoinMethod.ONLINE_DC)
    real = [(1, maps[0]), (2, maps[1]), (3, maps[2]), (5, maps[4]), (6, maps[5]), (7, maps[6])]
    real_after = [(12 + k, maps[11 + k]) for k in range(len(maps) - 11)]
    for seq, m in [*real, (9, stranger[0]), (10, stranger[1]), *real_after]:
        j.offer(m, seq)
    j.flush()
    n_real = len(real) + len(real_after)
    assert _sizes(j) == [(0, n_real), (1, 2)]  # the stranger stays apart, and the main island holds every real submap
    assert [c.island for c in j.state.chains] == [0, 1, 0]  # chains 0 and 1 were joined; labels follow the indices
    joined = global_result(j.state)
    held = set(joined.keys.tolist()) | {2 * joined.frame_id}
    assert all(set(m.keys.tolist()) <= held for _, m in real + real_after)
    _assert_exact(joined, run_join(maps, JoinMethod.ONLINE_DC).result)
    _assert_exact(island_map(j.state, 1), run_join(stranger, JoinMethod.ONLINE_DC).result)


def test_parts_that_link_only_with_each_other_are_joined_first_and_exactly():
    """Two submaps that each share one feature with the map (too few in 2D) but a pose with each
    other: joined with each other first, their union links with the map through two features."""
    world = make_world(2, 30, 40, np.random.default_rng(61))
    maps = exact_local_maps(world, np.random.default_rng(62), poses_per_map=2, sensor_range=8.0)
    truth = run_join(maps, JoinMethod.ONLINE_DC).result  # exact
    prefix = run_join(maps[:3], JoinMethod.ONLINE_DC).result  # maps[3] is lost: no common pose with maps[4:]
    x_map, y_map = maps[4], maps[5]
    f_x = int(np.intersect1d(x_map.feature_ids, prefix.feature_ids)[0])
    f_y = int(next(f for f in np.intersect1d(y_map.feature_ids, prefix.feature_ids) if f != f_x))
    renamed = []
    for m, keep in ((x_map, f_x), (y_map, f_y)):  # every other feature renamed: one common feature each
        ids = np.where((m.kinds == FEATURE) & (m.ids != keep), m.ids + 1000, m.ids)
        renamed.append(m.replace(ids=ids))
    x_map, y_map = renamed
    assert find_link(prefix, x_map) is None and find_link(prefix, y_map) is None
    assert find_link(x_map, y_map) is not None and find_link(x_map, y_map).pose_id == x_map.end_id
    parts = join_linked([(("prefix",), prefix), (("x",), x_map), (("y",), y_map)])  # type: ignore[list-item]
    assert len(parts) == 1 and sorted(parts[0][0]) == ["prefix", "x", "y"]
    joined = parts[0][1]
    assert joined.n_vars == len(set(prefix.keys.tolist()) | set(x_map.keys.tolist()) | set(y_map.keys.tolist())
                                | {2 * prefix.frame_id, 2 * x_map.frame_id}) - 1  # every variable once, but its frame pose
    _assert_exact(joined, truth)  # the renamed features are not in the truth: the rest is exact


def test_an_arrival_does_not_form_another_robot_s_map_to_see_whether_it_links(monkeypatch):
    """Whether a submap shares a variable with another island's chain is asked of the stack's parts: forming
    that chain's map (it changes at each of its robot's arrivals) cost hundreds of ms an arrival at 300 each."""
    import linear_slam_ros.joiner.islands as islands_module

    a = noisy_local_maps(make_world(2, 60, 80, np.random.default_rng(1)), np.random.default_rng(2), steps_per_map=3)
    b = noisy_local_maps(make_world(2, 60, 80, np.random.default_rng(3)), np.random.default_rng(4), steps_per_map=3)
    b = [m.replace(ids=np.where(m.kinds == FEATURE, m.ids + 10**6, m.ids)) for m in b]  # no common feature
    formed = []
    keys = islands_module.IslandCache.keys
    monkeypatch.setattr(islands_module.IslandCache, "keys", lambda self, *args: formed.append(1) or keys(self, *args))
    j = Joiner(JoinMethod.ONLINE_DC, defer_above=100)
    for i, (ma, mb) in enumerate(zip(a, b, strict=True), start=1):
        j.offer(ma, i, "a")
        j.offer(qualify(mb, 1), i, "b")
    assert len(j.state.islands) == 2 and j.state.n_joined == 2 * len(a) and formed == []


def test_a_third_island_bridging_two_links_all_three():
    """Robot b shares feature 1 with island A, robot c feature 2; then c measures b's pose: B and C are one
    island, which shares features 1 and 2 with A (enough in 2D). A, tested before B grew and never touched
    again, was left apart."""
    from linear_slam_ros.evaluation.runner import run_joiner
    from linear_slam_ros.evaluation.synthetic import World, exact_map

    s = ROBOT_ID_STRIDE
    rng = np.random.default_rng(0)
    poses = {0: [0, 0, 0], 1: [2, 0, 0.3], 2: [4, 1, 0.6], s: [0, 5, 2.0], s + 1: [1, 6, 2.5],
             2 * s: [6, 5, -1.0], 2 * s + 1: [5, 6, -2.9], 2 * s + 2: [3, 7, 3.1]}
    features = {1: [1, 3], 2: [5, 3], 10: [2, -2], 11: [3, -1], 20: [-1, 6], 21: [0, 8], 30: [7, 7], 31: [6, 8]}
    ids = sorted(poses)
    where = {k: i for i, k in enumerate(ids)}
    world = World(2, np.array([poses[k] for k in ids], float), {f: np.array(v, float) for f, v in features.items()})

    def submap(frame, pose_ids, feature_ids, end, name):
        m = exact_map(world, where[frame], [where[p] for p in pose_ids], feature_ids, rng, where[end], name)
        real = np.array([ids[int(i)] if k == 0 else int(i) for i, k in zip(m.ids, m.kinds, strict=True)])
        return m.replace(ids=real, frame_id=frame, end_id=end)

    stream = [
        ("a", 1, submap(0, [1], [10, 11, 1, 2], 1, "a1")),
        ("a", 2, submap(1, [2], [10, 11], 2, "a2")),
        ("b", 1, submap(s, [s + 1], [1, 20, 21], s + 1, "b1")),  # feature 1 of A: not enough alone
        ("c", 1, submap(2 * s, [2 * s + 1], [2, 30, 31], 2 * s + 1, "c1")),  # feature 2 of A: not enough alone
        ("c", 2, submap(2 * s + 1, [2 * s + 2, s + 1], [30], 2 * s + 2, "c2")),  # b's pose: B and C linked
    ]
    _, saved = run_joiner([m for _, _, m in stream], "online-dc", seqs=[q for _, q, _ in stream],
                          robots=[r for r, _, _ in stream])
    assert [(i.label, i.n_submaps) for i in saved.state.islands] == [(0, 5)]


def _two_robot_state(maps, robots: tuple[str, ...]):
    j = Joiner(JoinMethod.ONLINE_DC, robots=robots)
    for seq in (1, 2):
        j.offer(maps[seq - 1], seq, robots[0])
        j.offer(qualify(maps[6 + seq], 1), seq, robots[1])
    return j.save()


def test_a_restore_that_would_give_a_robot_another_s_slot_is_refused(maps, tmp_path):
    """Resumed with robots [b, a], robot b's submaps took robot a's pose ids and continued a's chain, silently."""
    path = tmp_path / "state.npz"
    write_snapshot(path, _two_robot_state(maps, ("a", "b")))
    saved = read_snapshot(path)
    assert saved.state.robots == ("a", "b")  # recorded, and through the state file
    for robots in (("b", "a"), ("a", "c"), ("b",)):
        expected = r"joined with robots=\['a', 'b'\], this joiner runs robots=" + re.escape(str(list(robots)))
        with pytest.raises(ConfigError, match=expected):
            Joiner(JoinMethod.ONLINE_DC, robots=robots).restore(saved)
    grown = Joiner(JoinMethod.ONLINE_DC, robots=("a", "b", "c"))  # a robot added at the end: every slot kept
    grown.restore(saved)
    assert grown.state.robots == ("a", "b", "c")
    shrunk = Joiner(JoinMethod.ONLINE_DC, robots=("a",))  # b removed at the end: its slot stays reserved
    shrunk.restore(saved)
    assert shrunk.state.robots == ("a", "b")
    with pytest.raises(ConfigError, match=r"joined with robots=\['a', 'b'\], this joiner runs robots=\['a', 'c'\]"):
        Joiner(JoinMethod.ONLINE_DC, robots=("a", "c")).restore(shrunk.save())  # c may not take b's slot later
    shrunk.reset()
    assert shrunk.state.robots == ("a",)  # an empty map holds no robot's poses
    single = Joiner(JoinMethod.ONLINE_DC)
    single.offer(maps[0], 1)
    Joiner(JoinMethod.ONLINE_DC, robots=("a", "b")).restore(single.save())  # one robot's map: robot a is slot 0


def test_a_state_file_without_the_robots_order_is_checked_by_name(maps, caplog):
    from test_snapshot import _rewritten

    from linear_slam_ros.joiner.snapshot import decode_state

    j = Joiner(JoinMethod.ONLINE_DC, robots=("a", "b"))
    j.restore(_two_robot_state(maps, ("a", "b")))
    older = decode_state(_rewritten(j, lambda fields: fields.pop("robots"), 7))  # a file as format 7 wrote it
    assert older.state.robots == () and {s.robot for s in older.state.streams} == {"a", "b"}
    assert "format version 7" not in caplog.text  # read with no warning: nothing else changed
    with pytest.raises(ConfigError, match=r"the saved map has robots \['a', 'b'\], not all in robots=\['a', 'c'\]"):
        Joiner(JoinMethod.ONLINE_DC, robots=("a", "c")).restore(older)
    with caplog.at_level(logging.WARNING):
        j = Joiner(JoinMethod.ONLINE_DC, robots=("a", "b"))
        j.restore(older)
    assert "does not record its robots' order" in caplog.text and j.state.robots == ("a", "b")
    Joiner(JoinMethod.ONLINE_DC).restore(older)  # a joiner given no robots (a library caller's own slots): as before


def test_chains_joined_when_islands_meet_defer_their_merges_as_every_chain_does():
    """They were re-seeded without the joiner's deferral: the running state then differed from the same state saved
    and restored (restore applies it), and later merges on that chain ran on arrival, not in the background."""
    world = make_world(2, 40, 30, np.random.default_rng(3))
    maps = noisy_local_maps(world, np.random.default_rng(4), steps_per_map=3, sensor_range=7.0)
    j = Joiner(JoinMethod.ONLINE_DC, defer_above=0, reorder_window=1)
    for seq, m in enumerate(maps, start=1):
        if seq not in (5, 10):  # two lost submaps: three islands, the first two frozen and joined into one chain
            j.offer(m, seq)
    j.flush()
    assert len(j.state.chains) == 2 and [c.n_joined for c in j.state.chains] == [8, 4]
    assert [c.joined.defer_above for c in j.state.chains] == [0, 0]
    restored = Joiner(JoinMethod.ONLINE_DC, defer_above=0)
    restored.restore(j.save())
    assert restored.state == j.state  # one value, equal to itself through a save and a restore
