"""Forward loop closures held back by the joiner until the chain reaches their pose, and gated then."""

from __future__ import annotations

import re

import numpy as np
import pytest

from linear_slam_ros.core.errors import FrameError
from linear_slam_ros.core.local_map import POSE, LocalMap
from linear_slam_ros.joiner.joiner import Joiner, due_closures, global_result, join_held, submap_step
from linear_slam_ros.joiner.snapshot import decode_state, encode_state
from linear_slam_ros.joiner.strategy import JoinMethod
from linear_slam_ros.joining.divide_conquer import online_dc_result

GATE = 0.99999999


def _stars(n: int = 30, seed: int = 5, lag: int = 3) -> list[LocalMap]:
    """Noisy 2D stars from pose k: odometry to k + 1 (end pose), a loop closure to k + lag while the chain reaches it."""
    rng = np.random.default_rng(seed)
    maps = []
    for k in range(n):
        x = np.array([1.0, 0.0, 0.0, float(lag), 0.0, 0.0]) + rng.normal(scale=0.01, size=6)
        m = 2 if k + lag <= n else 1
        maps.append(LocalMap(2, k, k + 1, np.array([k + 1, k + lag])[:m], np.full(m, POSE, dtype=np.int8), x[:3 * m],
                             1e4 * np.eye(3 * m), f"star_{k}"))
    return maps


def _run(joiner: Joiner, maps: list[LocalMap]) -> Joiner:
    for seq, m in enumerate(maps, start=1):
        assert joiner.offer(m, seq) == [seq]
    return joiner


@pytest.mark.parametrize("mode", [JoinMethod.ONLINE_DC, JoinMethod.SEQUENTIAL])
def test_with_the_gate_closures_are_held_until_the_chain_reaches_them_and_then_joined(mode):
    maps = _stars()
    j = Joiner(mode, gate_probability=GATE)
    assert j.state.hold_closures  # holding follows the gate by default
    _run(j, maps[:2])
    assert [(h.seq, h.origin, h.target) for h in j.state.held] == [(1, 0, 3), (2, 1, 4)]
    j.offer(maps[2], 3)  # its end pose is 3: the closure 0 -> 3 is joined with it
    assert [(h.seq, h.target) for h in j.state.held] == [(2, 4), (3, 5)]
    for seq in range(4, len(maps) + 1):
        j.offer(maps[seq - 1], seq)
    assert j.state.held == () and j.state.n_joined == len(maps) and j.gated == [] and not j.rejected
    plain = _run(Joiner(mode, hold_closures=True), maps)  # holding without the gate: the same map
    assert not _run(Joiner(mode), maps).state.hold_closures
    a, b = global_result(j.state), global_result(plain.state)
    assert a.keys.tolist() == b.keys.tolist() and np.array_equal(a.x, b.x)


def test_the_gate_on_without_holding_fuses_closures_on_arrival():
    j = _run(Joiner(JoinMethod.ONLINE_DC, gate_probability=GATE, hold_closures=False), _stars()[:5])
    assert j.state.held == () and not j.state.hold_closures
    assert global_result(j.state).has_pose(7)  # the closure 4 -> 7 brought pose 7 in ahead of the chain


def test_a_wrong_closure_is_gated_when_the_chain_reaches_its_pose_and_the_map_is_the_one_without_it():
    maps = _stars()
    bad = list(maps)
    x = maps[9].x.copy()
    x[3:5] += [1.5, -1.0]  # the closure 9 -> 12 moved by 1.8 m
    x[5] += np.deg2rad(20.0)
    bad[9] = maps[9].replace(x=x)
    without = list(maps)
    without[9] = LocalMap(2, 9, 10, np.array([10]), np.array([POSE], dtype=np.int8), maps[9].x[:3], 1e4 * np.eye(3),
                          "star_9")
    j = Joiner(JoinMethod.ONLINE_DC, gate_probability=GATE)
    messages: list[tuple[str, str]] = []
    j.on_reject = lambda reason, message: messages.append((reason, message))
    _run(j, bad)
    (record,) = j.gated
    assert (record.submap, record.name, record.variables, record.kinds, record.rejected) == (10, "star_9", (12,), (POSE,), False)
    assert record.dof == 3 and record.nis > record.threshold
    assert j.rejected == {"gated": 1} and j.state.n_joined == len(maps)
    (reason, message), = messages
    assert reason == "gated"
    assert "loop closure 9 -> 12 of submap seq 10 ('star_9'), held until the chain reached pose 12" in message
    assert "(probability 0.99999999" in message  # not rounded to 1
    ref = _run(Joiner(JoinMethod.ONLINE_DC, gate_probability=GATE), without)
    a, b = global_result(j.state), global_result(ref.state)
    assert a.keys.tolist() == b.keys.tolist() and np.array_equal(a.x, b.x)


def test_a_closure_that_cannot_be_joined_is_dropped_and_counted_and_its_submap_stays(monkeypatch):
    import linear_slam_ros.joiner.joiner as joiner_module

    maps = _stars(8)
    j = Joiner(JoinMethod.ONLINE_DC, gate_probability=GATE)
    _run(j, maps[:2])

    def refuse(state, closure, robot=""):
        raise FrameError(f"held closure {closure.name!r} refused")

    monkeypatch.setattr(joiner_module, "join_held", refuse)
    messages: list[tuple[str, str]] = []
    j.on_reject = lambda reason, message: messages.append((reason, message))
    assert j.offer(maps[2], 3) == [3]  # reaches pose 3: the closure 0 -> 3 fails, the submap is joined
    assert j.state.n_joined == 3 and j.rejected == {"held_closure": 1}
    (reason, message), = messages
    assert reason == "held_closure"
    assert re.search(r"loop closure 0 -> 3 of submap seq 1 \('star_0'\), held until the chain reached pose 3, not "
                     r"joined: held closure 'star_0/closure_3' refused", message)
    assert [h.target for h in j.state.held] == [4, 5]


def test_join_held_refuses_a_closure_not_at_the_chain_end_and_due_closures_needs_a_chain():
    maps = _stars(8)
    j = _run(Joiner(JoinMethod.ONLINE_DC, hold_closures=True), maps[:2])
    closure = j.state.held[1].in_target_frame()  # 1 -> 4, in pose 4's frame: the chain ends at pose 2
    with pytest.raises(FrameError, match=r"held closure 'star_1/closure_4' is in the frame of pose 4, not the end of "
                                         r"the chain of robot '' \(pose 2\)"):
        join_held(j.state, closure)
    with pytest.raises(FrameError, match=r"not the end of the chain of robot 'other' \(pose None\)"):
        join_held(j.state, closure, "other")
    assert due_closures(j.state, "other") == (j.state, ())


def test_a_submap_step_is_pure_and_a_held_state_saves_and_restores_exactly():
    maps = _stars(12)
    j = _run(Joiner(JoinMethod.ONLINE_DC, gate_probability=GATE), maps[:5])
    state = j.state
    step = submap_step(state, maps[5], 6, "", GATE)
    again = submap_step(state, maps[5], 6, "", GATE)
    assert j.state is state and [h.target for h in state.held] == [6, 7]  # the input state is untouched
    assert [(c.seq, c.target) for c, _ in step.released] == [(4, 6)] and step.joined and step.failed == ()
    assert np.array_equal(online_dc_result(step.state.joined).x, online_dc_result(again.state.joined).x)
    back = decode_state(encode_state(j.save()))
    assert back.state.hold_closures and [(h.seq, h.origin, h.target, h.name) for h in back.state.held] == [
        (h.seq, h.origin, h.target, h.name) for h in state.held]
    assert all(np.array_equal(a.measured.x, b.measured.x) and np.array_equal(a.measured.info, b.measured.info)
               for a, b in zip(back.state.held, state.held, strict=True))
    restored = Joiner(JoinMethod.ONLINE_DC, gate_probability=GATE)
    restored.restore(back)
    for seq in range(6, len(maps) + 1):
        j.offer(maps[seq - 1], seq)
        restored.offer(maps[seq - 1], seq)
    assert np.array_equal(global_result(j.state).x, global_result(restored.state).x)


def test_a_version_6_file_is_read_with_nothing_held(caplog):
    from test_snapshot import _rewritten

    j = _run(Joiner(JoinMethod.ONLINE_DC, gate_probability=GATE), _stars(6)[:2])

    def as_version_6(fields):
        fields.pop("hold_closures")
        fields.pop("held")

    back = decode_state(_rewritten(j, as_version_6, 6))
    assert back.state.held == () and not back.state.hold_closures
    assert back.state.variance == j.state.variance and back.state.n_joined == 2
    assert np.array_equal(online_dc_result(back.state.joined).x, online_dc_result(j.state.joined).x)
    assert "format version 6" not in caplog.text  # nothing is lost: no warning



def _chain(first: int, n: int, closures: dict[int, int] | None = None) -> list[LocalMap]:
    """Odometry stars from pose ``first`` on (1 m forward each), with loop closures ``{k: target}`` (exact)."""
    out = []
    for k in range(first, first + n):
        target = (closures or {}).get(k)
        ids = [k + 1] if target is None else [k + 1, target]
        x = [1.0, 0.0, 0.0] if target is None else [1.0, 0.0, 0.0, float(target - k) if target < 100 else 0.0, 5.0, 0.0]
        out.append(LocalMap(2, k, k + 1, np.array(ids), np.full(len(ids), POSE, dtype=np.int8), np.array(x),
                            1e2 * np.eye(3 * len(ids)), f"{first}_{k}"))
    return out


def test_a_held_closure_to_another_robots_pose_links_the_islands_when_that_robot_reaches_it():
    a = _chain(0, 8, {3: 105})  # robot a's submap from pose 3 closes on pose 105, which robot b reaches later
    b = _chain(100, 8)
    j = Joiner(JoinMethod.ONLINE_DC, hold_closures=True)
    for i in range(8):
        j.offer(a[i], i + 1, "a")
        j.offer(b[i], i + 1, "b")
        if i == 3:
            assert [(h.robot, h.origin, h.target) for h in j.state.held] == [("a", 3, 105)]
            assert len(j.state.islands) == 2
    assert j.state.held == () and len(j.state.islands) == 1 and j.state.n_joined == 16
    apart = Joiner(JoinMethod.ONLINE_DC, hold_closures=True)
    for i in range(8):
        apart.offer(_chain(0, 8)[i], i + 1, "a")
        apart.offer(b[i], i + 1, "b")
    assert len(apart.state.islands) == 2  # without the closure the two robots' maps stay apart


def test_a_closure_to_a_pose_another_island_already_holds_is_not_held():
    b = _chain(100, 8)
    j = Joiner(JoinMethod.ONLINE_DC, hold_closures=True)
    for i in range(8):
        j.offer(b[i], i + 1, "b")
    a = _chain(0, 5, {2: 104})
    for i in range(5):
        j.offer(a[i], i + 1, "a")
    assert j.state.held == () and len(j.state.islands) == 1


def test_the_fresh_pose_chains_across_a_held_closure():
    """A released closure is a part of the chain whose end is its frame: the cheap current pose is still the chain's end.

    (Chained along the stack's parts, it is not the joined map's estimate, only near it.)
    """
    from linear_slam_ros.joiner.joiner import current_pose

    maps = _stars(12)
    j = _run(Joiner(JoinMethod.ONLINE_DC, hold_closures=True), maps)
    fresh = current_pose(j.state)
    assert fresh is not None and fresh[0] == 12
    exact = global_result(j.state, "first_pose")
    assert np.linalg.norm(fresh[1][:2] - exact.pose(12)[:2]) < 0.05 and abs(fresh[1][2] - exact.pose(12)[2]) < 0.05


def test_closures_beyond_max_held_are_dropped_oldest_first_and_counted():
    from linear_slam_ros.core.errors import ConfigError

    maps = _stars(20, lag=8)  # each submap k closes on pose k + 8: up to 7 wait at once
    j = Joiner(JoinMethod.ONLINE_DC, hold_closures=True, max_held=3)
    messages: list[tuple[str, str]] = []
    j.on_reject = lambda reason, message: messages.append((reason, message))
    _run(j, maps[:5])
    assert [h.target for h in j.state.held] == [10, 11, 12]
    assert j.rejected == {"held_closure": 2}
    assert messages[0] == ("held_closure", "loop closure 0 -> 8 of submap seq 1 ('star_0') dropped: more than "
                                           "max_held=3 closures wait for their pose (pose 8 not reached)")
    with pytest.raises(ConfigError, match=r"max_held=-1 must be >= 0"):
        Joiner(JoinMethod.ONLINE_DC, max_held=-1)


def test_set_gate_turns_holding_on_and_off_unless_it_is_set_apart():
    from linear_slam_ros.core.errors import ConfigError

    j = Joiner(JoinMethod.ONLINE_DC)
    assert not j.state.hold_closures
    j.set_gate(GATE)
    assert j.gate_probability == GATE and j.state.hold_closures
    j.set_gate(None)
    assert not j.state.hold_closures
    kept = Joiner(JoinMethod.ONLINE_DC, hold_closures=True)
    kept.set_gate(None)
    assert kept.state.hold_closures
    with pytest.raises(ConfigError, match=r"gate_probability=1\.0 must be in \[0, 1\)"):
        j.set_gate(1.0)
    assert j.gate_probability is None


def test_cli_join_with_hold_closures_reports_them(tmp_path, monkeypatch):
    import json

    from linear_slam_ros.cli.main import main
    from support import CACHE, dataset_archive

    monkeypatch.setenv("LINEAR_SLAM_CACHE", str(CACHE))
    archive = str(dataset_archive("Intel"))
    assert main(["join", archive, "--method", "online-dc", "--hold-closures", "--out", str(tmp_path / "held")]) == 0
    report = json.loads((tmp_path / "held" / "report.json").read_text())
    assert report["hold_closures"] is True and report["n_held"] == 0 and "gated" not in report
    assert round(report["chi2"], 2) == 546.56  # 546.51 with the closures fused on arrival (README, "Gating")
    assert main(["join", archive, "--method", "online-dc", "--out", str(tmp_path / "plain")]) == 0
    plain = json.loads((tmp_path / "plain" / "report.json").read_text())
    assert "hold_closures" not in plain and round(plain["chi2"], 2) == 546.51


def test_on_fused_gives_the_measurements_of_the_joined_map_as_measured():
    """What a refiner is given: every measurement but the gated closure, each in its submap's frame."""
    from linear_slam_ros.refinement.online import refine_offline

    maps = _stars()
    bad = list(maps)
    x = maps[9].x.copy()
    x[3:5] += [1.5, -1.0]
    x[5] += np.deg2rad(20.0)
    bad[9] = maps[9].replace(x=x)
    j = Joiner(JoinMethod.ONLINE_DC, gate_probability=GATE)
    fused: dict[int, tuple[LocalMap, ...]] = {}
    j.on_fused = lambda robot, seq, ms: fused.__setitem__(seq, ms)
    _run(j, bad)
    assert [(m.frame_id, m.ids.tolist()) for m in fused[11]] == [(10, [11]), (8, [11])]  # closure 8 -> 11 joined with it
    assert [(m.frame_id, m.ids.tolist()) for m in fused[12]] == [(11, [12])]  # 9 -> 12 was gated: not there
    assert len(j.gated) == 1
    measurements = [m for seq in sorted(fused) for m in fused[seq]]
    without = [m if k != 9 else LocalMap(2, 9, 10, np.array([10]), np.array([POSE], dtype=np.int8), m.x[:3],
                                         1e4 * np.eye(3), m.name) for k, m in enumerate(maps)]
    got, ref = refine_offline(measurements), refine_offline(without)
    assert got.chi2 == pytest.approx(ref.chi2, rel=1e-8)
    plain = Joiner(JoinMethod.ONLINE_DC)
    seen: dict[int, tuple[LocalMap, ...]] = {}
    plain.on_fused = lambda robot, seq, ms: seen.__setitem__(seq, ms)
    _run(plain, maps)
    assert all(seen[seq] == (maps[seq - 1],) for seq in seen)  # neither gate nor holding: the submap itself


@pytest.mark.parametrize("mode", [JoinMethod.ONLINE_DC, JoinMethod.SEQUENTIAL])
def test_the_poses_a_star_submap_passes_through_are_joined_not_held(mode):
    """A star chunk of two steps (frame 2k, poses 2k+1 and 2k+2 = its end, one block per edge): its
    intermediate pose is uncoupled and new, but it is its own path, not a closure. Held, it waited for
    a chain end that passed it by: half the trajectory was missing with the gate on."""
    rng = np.random.default_rng(0)
    maps = []
    for k in range(10):
        f = 2 * k
        x = np.array([1.0, 0.0, 0.0, 2.0, 0.0, 0.0]) + rng.normal(scale=0.01, size=6)
        info = np.diag([400.0, 400.0, 900.0, 200.0, 200.0, 500.0])
        maps.append(LocalMap(2, f, f + 2, np.array([f + 1, f + 2]), np.array([POSE, POSE], dtype=np.int8), x, info, f"s{k}"))
    for kwargs in ({"hold_closures": True}, {"gate_probability": 0.99999999}):
        j = Joiner(mode, **kwargs)
        for seq, m in enumerate(maps, start=1):
            assert j.offer(m, seq) == [seq]
        assert sorted(global_result(j.state).pose_ids.tolist()) == list(range(20)) and j.state.held == ()  # 20: the frame


def test_a_submap_failing_only_on_its_end_pose_is_joined_and_not_reported_as_gated(caplog):
    """Holding off, a wrong forward closure 0 -> 3 is fused on arrival; submap 3's end pose then fails the gate.
    The end pose cannot be split off: it was recorded 'gated whole' with nothing kept out (three false records)."""
    rng = np.random.default_rng(5)
    maps = []
    for k in range(12):
        x = np.array([1.0, 0.0, 0.0, 3.0, 0.0, 0.0]) + rng.normal(scale=0.01, size=6)
        if k == 0:
            x[3:5] += [1.5, -1.0]  # the closure 0 -> 3 is wrong by 1.8 m
        m = 2 if k + 3 <= 12 else 1
        maps.append(LocalMap(2, k, k + 1, np.array([k + 1, k + 3])[:m], np.full(m, POSE, dtype=np.int8), x[: 3 * m],
                             1e4 * np.eye(3 * m), f"star_{k}"))
    gated = Joiner(JoinMethod.ONLINE_DC, gate_probability=0.99999999, hold_closures=False)
    plain = Joiner(JoinMethod.ONLINE_DC, hold_closures=False)
    for seq, m in enumerate(maps, start=1):
        gated.offer(m, seq)
        plain.offer(m, seq)
    assert not any(g.submap == 3 for g in gated.gated)
    assert "submap 'star_2' fails the gate (NIS 7737.5 > 122.9 for 3 dof) on its end pose only" in caplog.text
    a, b = global_result(gated.state), global_result(plain.state)
    assert a.keys.tolist() == b.keys.tolist() and np.allclose(a.x, b.x, atol=1e-12)  # joined as it is, and said so
