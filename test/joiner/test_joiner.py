"""Joiner state machine: sequencing, duplicates, gaps, rejection counts, unchanged map on bad input."""

from __future__ import annotations

import numpy as np
import pytest

from linear_slam_ros.core.errors import ConfigError
from linear_slam_ros.core.local_map import POSE, LocalMap
from linear_slam_ros.evaluation.runner import run_join
from linear_slam_ros.evaluation.synthetic import make_world, noisy_local_maps
from linear_slam_ros.joiner.joiner import Joiner
from linear_slam_ros.joiner.snapshot import read_snapshot, write_snapshot
from linear_slam_ros.joiner.strategy import JoinMethod
from linear_slam_ros.joining.background import MergeWorker
from linear_slam_ros.joining.divide_conquer import Deferred
from linear_slam_ros.joining.islands import poses_of
from support import FakeClock, global_map_of


@pytest.fixture
def maps():
    world = make_world(2, 24, 20, np.random.default_rng(11))
    return noisy_local_maps(world, np.random.default_rng(12), steps_per_map=3)


@pytest.mark.parametrize("mode", [JoinMethod.SEQUENTIAL, JoinMethod.ONLINE_DC])
def test_in_order_stream_equals_offline(mode, maps):
    j = Joiner(mode)
    for seq, m in enumerate(maps, start=1):
        assert j.offer(m, seq) == [seq]
    online = global_map_of(j.state)
    offline = run_join(maps, mode).result
    np.testing.assert_array_equal(online.x, offline.x)
    assert j.stats()["n_joined"] == len(maps) and j.n_rejected == 0
    assert global_map_of(j.state, "first_pose").frame_id == 0


def test_out_of_order_duplicates_and_gaps(maps):
    reasons = []
    j = Joiner(JoinMethod.SEQUENTIAL, reorder_window=2)
    j.on_reject = lambda reason, message: reasons.append((reason, message))
    assert j.offer(maps[0], 1) == [1]
    assert j.offer(maps[2], 3) == []  # early: waits for 2
    assert j.offer(maps[1], 2) == [2, 3]  # the gap fills
    assert j.offer(maps[1], 2) == []  # sent again (a replayed bag, a restarted front-end)
    assert j.offer(maps[2], 3) == []
    assert reasons == [] and j.n_skipped == 2  # skipped, not rejections
    # seq 4 never arrives: after the window fills, the gap is skipped and the rest is tried
    assert j.offer(maps[4], 5) == []
    assert j.offer(maps[5], 6) == []
    joined = j.offer(maps[6], 7)
    assert "gap" in dict(reasons) and "submaps seq 4..4 never arrived or were rejected" in dict(reasons)["gap"]
    # seq 5 starts at pose 12, not in the map (it ends at 9): after the gap it starts an island, and 6, 7 continue it
    assert joined == [5, 6, 7] and "FrameError" not in j.rejected
    # the island shares features with the map: linked at once, one island of two chains
    assert [(s.label, s.n_submaps, s.chains) for s in j.state.islands] == [(0, 6, (0, 1))]
    assert set(poses_of(global_map_of(j.state)).tolist()) >= set(poses_of(maps[6]).tolist())


def test_rejected_submap_leaves_the_map_unchanged(maps):
    j = Joiner(JoinMethod.SEQUENTIAL)
    j.offer(maps[0], 1)
    before = global_map_of(j.state)
    assert j.offer(maps[3], 2) == []  # frame pose 9 is not in the map
    assert j.rejected["FrameError"] == 1
    after = global_map_of(j.state)
    assert after.x.tobytes() == before.x.tobytes() and j.state.n_joined == 1
    assert j.offer(maps[1], 2) == [2]  # the valid 2 comes: the stream goes on
    j.reset()
    assert j.state.n_joined == 0 and j.n_rejected == 0 and global_map_of(j.state) is None


def test_save_and_restore_carry_on_exactly(maps):
    j = Joiner(JoinMethod.ONLINE_DC, reorder_window=5)
    j.offer(maps[0], 1)
    j.offer(maps[4], 2)  # wrong frame: rejected
    j.offer(maps[3], 4)  # early: waits in the buffer
    j.offer(maps[0], 1)  # sent again: skipped
    saved = j.save(journal_records=4)
    assert [s for s, _ in saved.pending] == [4] and dict(saved.rejected) == {"FrameError": 1} and saved.n_skipped == 1
    assert saved.state.next_seq == 2 and saved.journal_records == 4  # the rejected 2 stays open
    other = Joiner(JoinMethod.ONLINE_DC, reorder_window=5)
    other.gated.append("a decision on the map it replaces")  # type: ignore[arg-type]
    other.reinitialised.append("likewise")  # type: ignore[arg-type]
    other.restore(saved)
    assert other.gated == [] and other.reinitialised == []  # the records restart with the restored map
    for joiner in (j, other):
        assert joiner.offer(maps[1], 2) == [2]
        assert joiner.offer(maps[2], 3) == [3, 4]  # 3 fills the gap, the buffered 4 follows
    np.testing.assert_array_equal(global_map_of(j.state).x, global_map_of(other.state).x)
    assert other.n_rejected == 1 and other.n_skipped == 1 and other.state.n_joined == 4
    with pytest.raises(ConfigError, match="the saved map was joined with mode='online-dc', map_type='as-is'; "
                                          "this joiner runs mode='sequential'"):
        Joiner(JoinMethod.SEQUENTIAL).restore(saved)


def test_background_merges_give_the_same_map_and_survive_save_restore_and_reset(maps, tmp_path):
    worker = MergeWorker()
    try:
        j = Joiner(JoinMethod.ONLINE_DC, defer_above=0, worker=worker)  # every merge in the background
        for seq, m in enumerate(maps[:6], start=1):
            assert j.offer(m, seq) == [seq]
        assert j.state.joined.defer_above == 0
        write_snapshot(tmp_path / "state.npz", j.save())  # deferred merges as their results or their inputs
        restored = read_snapshot(tmp_path / "state.npz")
        other = Joiner(JoinMethod.ONLINE_DC, defer_above=0, worker=worker)
        other.restore(restored)
        for seq, m in enumerate(maps[6:], start=7):
            assert j.offer(m, seq) == [seq] and other.offer(m, seq) == [seq]
        offline = run_join(maps, JoinMethod.ONLINE_DC).result
        for joiner in (j, other):
            np.testing.assert_array_equal(global_map_of(joiner.state).x, offline.x)
        pose_id, pose = j.state.strategy.current_pose(j.state.joined, j.state.first_pose_id)
        assert pose_id == offline.end_id and np.all(np.isfinite(pose))
        j.reset()
        assert j.state.n_joined == 0 and j.state.joined.defer_above == 0 and worker.wait_idle(30.0)
    finally:
        worker.stop()
    assert not worker.alive


def test_a_restored_states_deferred_merges_go_to_the_worker_at_once(maps, tmp_path):
    lazy = Joiner(JoinMethod.ONLINE_DC, defer_above=0)  # no worker: the merges stay to compute
    for seq, m in enumerate(maps[:6], start=1):
        lazy.offer(m, seq)
    write_snapshot(tmp_path / "state.npz", lazy.save())
    restored = read_snapshot(tmp_path / "state.npz")
    deferred = [e for e in restored.state.joined.stack if isinstance(e, Deferred)]
    assert deferred and not any(e.done for e in deferred)
    worker = MergeWorker()
    try:
        Joiner(JoinMethod.ONLINE_DC, defer_above=0, worker=worker).restore(restored)
        assert worker.wait_idle(30.0) and all(e.done for e in deferred)  # no join needed to start them
    finally:
        worker.stop()


def _joiner(**kw):
    reasons = []
    clock = FakeClock()
    j = Joiner(JoinMethod.SEQUENTIAL, clock=clock, **kw)
    j.on_reject = lambda reason, message: reasons.append((reason, message))
    return j, reasons, clock


def test_a_rejected_submap_leaves_its_number_to_a_valid_one(maps):
    j, reasons, _ = _joiner()
    assert j.offer(maps[0], 1) == [1]
    assert j.offer(maps[5], 2) == []  # wrong frame, carrying the next number
    assert j.offer(maps[2], 3) == []  # waits for 2
    assert j.offer(maps[1], 2) == [2, 3]  # the valid 2 still comes, and 3 follows
    assert [r for r, _ in reasons] == ["FrameError"] and j.n_skipped == 0


def test_sequence_numbers_start_at_1_and_a_far_first_message_cannot_move_the_stream(maps):
    j, reasons, clock = _joiner(reorder_window=3, reorder_timeout=1.0)
    assert j.offer(maps[0], 0) == [] and reasons[-1][0] == "seq_out_of_range"
    assert "sequence numbers start at 1" in reasons[-1][1]
    assert j.offer(maps[3], 10**9) == []  # waits, alone
    clock.t = 100.0
    assert j.expire() == []  # a lone far-ahead submap is never a credible next one
    assert [j.offer(m, s) for s, m in enumerate(maps[:4], start=1)] == [[1], [2], [3], [4]]
    assert j.state.n_joined == 4 and j.state.next_seq == 5


def test_a_node_started_mid_stream_moves_to_it_after_the_timeout(maps):
    j, reasons, clock = _joiner(reorder_window=100, reorder_timeout=2.0)
    assert j.offer(maps[3], 500) == [] and j.offer(maps[4], 501) == []  # two consecutive numbers, far ahead
    clock.t = 1.0
    assert j.expire() == []
    clock.t = 2.5
    assert j.expire() == [("", 500), ("", 501)]
    assert "submaps seq 1..499 never arrived or were rejected (no progress for 2.5 s)" in reasons[-1][1]


def test_a_gap_that_cannot_fill_is_skipped_after_the_timeout(maps):
    j, reasons, clock = _joiner(reorder_window=100, reorder_timeout=1.0)
    assert j.offer(maps[0], 1) == [1]
    assert j.offer(maps[2], 3) == []  # 2 never comes (it was undecodable), and few follow
    clock.t = 0.5
    assert j.expire() == []
    clock.t = 1.2
    assert j.expire() == [("", 3)]  # 3 starts at pose 6, the map ends at 3: skipped to, it starts an island
    assert [r for r, _ in reasons] == ["gap"] and len(j.state.islands) == 2


def test_after_an_idle_spell_a_gap_is_given_its_full_timeout(maps):
    """The timeout counts from the first submap that waits behind the gap, not from the stream's last join."""
    j, reasons, clock = _joiner(reorder_window=100, reorder_timeout=5.0)
    assert j.offer(maps[0], 1) == [1]
    clock.t = 60.0  # the robot paused for a minute, then 3 arrives before 2
    assert j.offer(maps[2], 3) == []
    clock.t = 60.1
    assert j.expire() == []  # 2 is 0.1 s late, not 60 s
    assert j.offer(maps[1], 2) == [2, 3] and reasons == []
    clock.t = 70.0
    assert j.offer(maps[4], 5) == []
    clock.t = 75.5
    assert j.expire() == [("", 5)] and "no progress for 5.5 s" in reasons[-1][1]


def test_a_lowered_byte_bound_with_several_robots_relieves_without_failing(maps):
    size = maps[3].nbytes
    j, reasons, _ = _joiner(reorder_window=20, reorder_max_bytes=100 * size)
    for seq in range(10, 20):  # robot a's early submaps: 10 wait
        j.offer(maps[3], seq, "a")
    j.reorder_max_bytes = 2 * size  # lowered behind the joiner's back: relieved at the next early submap
    assert j.offer(maps[3], 50, "b") == []  # b's lone far submap is dropped; a's bytes are a's to relieve: no error
    assert [r for r, _ in reasons] == ["reorder_buffer_full"] and "robot 'b' submap seq 50 dropped" in reasons[0][1]
    j.offer(maps[3], 30, "a")  # a's next early submap relieves a's buffer
    assert j._pending_bytes <= 2 * size


def test_lowered_reorder_bounds_bring_every_robots_buffer_within_them_at_once(maps):
    size = maps[3].nbytes
    j, reasons, _ = _joiner(reorder_window=20, reorder_max_bytes=100 * size)
    assert j.offer(maps[0], 1, "a") == [1]
    for seq in range(3, 9):  # a waits for 2: 6 early submaps
        j.offer(maps[seq - 1], seq, "a")
    for seq in (40, 50):  # b waits for its first: two lone far ones
        j.offer(maps[3], seq, "b")
    assert j.set_reorder(max_bytes=j._pending_bytes) == [] and reasons == []  # still within
    joined = j.set_reorder(window=2, max_bytes=size + 1)
    assert joined == [("a", s) for s in range(3, 9)]  # a: 2 given up (3 is credible), 3..8 joined
    assert [r for r, _ in reasons] == ["gap", "reorder_buffer_full"]  # b: its farthest dropped, 40 waits
    assert "robot 'b' submap seq 50 dropped" in reasons[1][1] and j.already_handled(40, "b")
    assert (j.reorder_window, j.reorder_max_bytes, j.reorder_timeout) == (2, size + 1, 5.0)
    assert j._pending_bytes == size


def test_the_reorder_buffer_is_bounded_in_count_and_bytes(maps):
    size = maps[3].x.nbytes + maps[3].ids.nbytes + maps[3].kinds.nbytes + np.asarray(maps[3].info).nbytes
    j, reasons, _ = _joiner(reorder_window=2, reorder_max_bytes=int(2.5 * size))
    assert j.offer(maps[0], 1) == [1]
    for far in (10**6, 10**7, 10**8):  # lone far-ahead submaps: never credible, the farthest is dropped
        j.offer(maps[3], far)
    assert [r for r, _ in reasons] == ["reorder_buffer_full"]
    assert "submap seq 100000000 dropped: it waits for seq 2 and the reorder buffer is full" in reasons[0][1]
    assert j.offer(maps[1], 2) == [2]  # the stream goes on
    j.reset()
    assert j.already_handled(10**6) is False  # reset empties the buffer


def test_an_empty_submap_uses_its_number_and_changes_nothing(maps):
    j, reasons, _ = _joiner()
    assert j.offer(maps[0], 1) == [1]
    before = global_map_of(j.state).x.tobytes()
    empty = maps[1].replace(ids=maps[1].ids[:0], kinds=maps[1].kinds[:0], x=maps[1].x[:0], info=np.zeros((0, 0)), end_id=None)
    assert j.offer(empty, 2) == [] and reasons == []
    assert global_map_of(j.state).x.tobytes() == before and j.expected == 3
    assert j.offer(maps[1].replace(name="m"), 3) == [3]  # the stream goes on (maps[1] starts where the map ends)


@pytest.mark.parametrize("mode", [JoinMethod.SEQUENTIAL, JoinMethod.ONLINE_DC])
def test_a_submap_that_would_leave_no_global_map_is_rejected_and_the_stream_goes_on(mode, maps):
    """Joined, a pose 100 m ahead with heading information 1e-3 and position information 1e10 (within
    every input limit) left no global map that could be factorised again."""
    reasons: list[tuple[str, str]] = []
    j = Joiner(mode, on_reject=lambda reason, message: reasons.append((reason, message)))
    for seq, m in enumerate(maps[:6], start=1):
        assert j.offer(m, seq) == [seq]
    before = global_map_of(j.state).x.tobytes()
    end = maps[5].end_id
    poison = LocalMap(2, end, end + 1000, np.array([end + 1000]), np.array([POSE], dtype=np.int8),
                      np.array([100.0, 0.0, 0.0]), np.diag([1e10, 1e10, 1e-3]), "poison")
    assert j.offer(poison, 7) == []
    assert reasons[-1][0] == "InvalidMapError" and "in the frame of its end pose" in reasons[-1][1]
    assert global_map_of(j.state).x.tobytes() == before
    assert j.offer(maps[6], 7) == [7]  # a valid submap takes the number and continues the chain
    assert global_map_of(j.state).n_vars > 0
