"""Joiner state machine: sequencing, duplicates, gaps, rejection counts, unchanged map on bad input."""

from __future__ import annotations

import numpy as np
import pytest

from linear_slam_ros.core.errors import ConfigError
from linear_slam_ros.evaluation.runner import run_join
from linear_slam_ros.evaluation.synthetic import make_world, noisy_local_maps
from linear_slam_ros.joiner.joiner import Joiner
from linear_slam_ros.joiner.strategy import JoinMethod
from support import global_map_of


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
    assert "gap" in dict(reasons) and "submaps seq 4..4 never arrived" in dict(reasons)["gap"]
    assert joined == []  # seq 5 starts at pose 12, not in the map (ends at 9): rejected, as are 6, 7
    assert j.rejected["FrameError"] == 3 and j.state.n_joined == 3


def test_rejected_submap_leaves_the_map_unchanged(maps):
    j = Joiner(JoinMethod.SEQUENTIAL)
    j.offer(maps[0], 1)
    before = global_map_of(j.state)
    assert j.offer(maps[3], 2) == []  # frame pose 9 is not in the map
    assert j.rejected["FrameError"] == 1
    after = global_map_of(j.state)
    assert after.x.tobytes() == before.x.tobytes() and j.state.n_joined == 1
    assert j.offer(maps[1], 3) == [3]  # the stream goes on
    j.reset()
    assert j.state.n_joined == 0 and j.n_rejected == 0 and global_map_of(j.state) is None


def test_save_and_restore_carry_on_exactly(maps):
    j = Joiner(JoinMethod.ONLINE_DC, reorder_window=5)
    j.offer(maps[0], 1)
    j.offer(maps[4], 2)  # wrong frame: rejected
    j.offer(maps[3], 5)  # early: waits in the buffer
    j.offer(maps[0], 1)  # sent again: skipped
    saved = j.save(journal_records=4)
    assert [s for s, _ in saved.pending] == [5] and dict(saved.rejected) == {"FrameError": 1} and saved.n_skipped == 1
    assert saved.state.next_seq == 3 and saved.journal_records == 4
    other = Joiner(JoinMethod.ONLINE_DC, reorder_window=5)
    other.restore(saved)
    for joiner in (j, other):
        assert joiner.offer(maps[1], 3) == [3]
        assert joiner.offer(maps[2], 4) == [4, 5]  # 4 fills the gap, the buffered 5 follows
    np.testing.assert_array_equal(global_map_of(j.state).x, global_map_of(other.state).x)
    assert other.n_rejected == 1 and other.n_skipped == 1 and other.state.n_joined == 4
    with pytest.raises(ConfigError, match="the saved map was joined with mode='online-dc', map_type='as-is'; "
                                          "this joiner runs mode='sequential'"):
        Joiner(JoinMethod.SEQUENTIAL).restore(saved)
