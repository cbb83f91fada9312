"""Joiner state machine: sequencing, duplicates, gaps, rejection counts, unchanged map on bad input."""

from __future__ import annotations

import numpy as np
import pytest

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
    assert j.offer(maps[1], 2) == []  # duplicate
    assert j.offer(maps[2], 3) == []  # late
    assert [r for r, _ in reasons] == ["duplicate_or_late", "duplicate_or_late"]
    assert "submap seq 2 arrived after seq 3 was handled" in reasons[0][1]
    # seq 4 never arrives: after the window fills, the gap is skipped and the rest is tried
    assert j.offer(maps[4], 5) == []
    assert j.offer(maps[5], 6) == []
    joined = j.offer(maps[6], 7)
    assert ("gap" in dict(reasons)) and "submaps seq 4..4 never arrived" in dict(reasons)["gap"]
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
