"""The joiner at its edges: other dimensions, gate probability 0, empty submaps in the buffer, byte bounds after
reset and restore, gap timers. (Found by a mutation audit: each test fails on a mutant the suite let through.)
"""

from __future__ import annotations

import numpy as np
import pytest

import linear_slam_ros.joiner.joiner as jm
from linear_slam_ros.core.local_map import LocalMap
from linear_slam_ros.evaluation.synthetic import make_world, noisy_local_maps
from linear_slam_ros.joiner.joiner import Joiner, island_map
from linear_slam_ros.joiner.strategy import JoinMethod
from support import FakeClock


@pytest.fixture(scope="module")
def maps():
    w = make_world(2, 30, 40, np.random.default_rng(1))
    return noisy_local_maps(w, np.random.default_rng(2), steps_per_map=3)


@pytest.fixture(scope="module")
def maps3():
    w = make_world(3, 30, 40, np.random.default_rng(1))
    return noisy_local_maps(w, np.random.default_rng(2), steps_per_map=3)


def _empty(frame):
    return LocalMap(2, frame, None, np.zeros(0, int), np.zeros(0, np.int8), np.zeros(0), np.zeros((0, 0)))


def test_a_submap_of_another_dimension_is_refused_by_name(maps, maps3):
    j = Joiner(JoinMethod.ONLINE_DC)
    assert j.offer(maps[0], 1) == [1]
    assert j.offer(maps3[1], 2) == [] and j.rejected["InvalidMapError"] == 1


def test_gate_probability_zero_is_off(maps):
    j = Joiner(JoinMethod.ONLINE_DC, gate_probability=0.0)
    for seq, m in enumerate(maps[:6], start=1):
        assert j.offer(m, seq) == [seq]
    assert j.n_rejected == 0


def test_an_empty_submap_in_the_buffer_does_not_stop_the_drain(maps):
    j = Joiner(JoinMethod.ONLINE_DC)
    assert j.offer(maps[0], 1) == [1]
    assert j.offer(_empty(maps[0].end_id), 3) == []
    assert j.offer(maps[2], 4) == []
    assert j.offer(maps[1], 2) == [2, 4] and j.expected == 5


def test_an_empty_submap_uses_up_its_number(maps):
    j = Joiner(JoinMethod.ONLINE_DC)
    j.offer(maps[0], 1)
    j.offer(_empty(maps[0].end_id), 2)
    assert j.state.last_seq == 2


def test_a_singular_system_is_a_rejection_not_a_crash(maps, monkeypatch):
    j = Joiner(JoinMethod.ONLINE_DC)
    monkeypatch.setattr(jm, "submap_step", lambda *a, **k: (_ for _ in ()).throw(np.linalg.LinAlgError("singular")))
    assert j.offer(maps[0], 1) == [] and j.rejected["LinAlgError"] == 1


def test_reset_forgets_the_buffered_bytes(maps):
    j = Joiner(JoinMethod.ONLINE_DC, reorder_max_bytes=int(1.5 * maps[2].nbytes))
    assert j.offer(maps[2], 3) == []
    j.reset()
    assert j.offer(maps[2], 3) == [] and j.n_rejected == 0


def test_restore_counts_the_buffered_bytes(maps):
    j = Joiner(JoinMethod.ONLINE_DC)
    j.offer(maps[0], 1)
    j.offer(maps[2], 3)
    k = Joiner(JoinMethod.ONLINE_DC, reorder_max_bytes=int(1.2 * max(maps[2].nbytes, maps[4].nbytes)))
    k.restore(j.save())
    k.offer(maps[4], 5)  # two waiting now: above the byte bound, the gap is skipped
    assert k.rejected["gap"] == 1


def test_a_gap_holds_the_stream_from_the_first_waiting_submap(maps):
    c = FakeClock()
    j = Joiner(JoinMethod.ONLINE_DC, clock=c, reorder_timeout=5.0)
    j.offer(maps[0], 1)
    c.t = 1.0
    j.offer(maps[2], 3)
    c.t = 5.0
    j.offer(maps[3], 4)
    c.t = 6.5
    j.expire()
    assert j.rejected["gap"] == 1


def test_no_other_island_without_islands(maps):
    j = Joiner(JoinMethod.ONLINE_DC)
    j.offer(maps[0], 1)
    assert island_map(j.state, 1) is None


def test_last_join_ms_is_in_milliseconds(maps):
    j = Joiner(JoinMethod.ONLINE_DC)
    j.offer(maps[0], 1)
    assert j.stats()["last_join_ms"] == pytest.approx(j.join_seconds[-1] * 1e3)


def test_a_submap_without_end_pose_keeps_the_chain_end(maps):
    j = Joiner(JoinMethod.ONLINE_DC)
    j.offer(maps[0], 1)
    j.offer(maps[1].replace(end_id=None), 2)
    assert j.state.chains[0].end_id == maps[0].end_id


def test_after_a_gap_a_submap_of_another_dimension_starts_no_island(maps, maps3):
    j = Joiner(JoinMethod.ONLINE_DC)
    assert j.offer(maps[0], 1) == [1]
    assert j.offer(maps3[2], 3) == [] and j.offer(maps3[3], 4) == []  # waiting behind the gap
    j.flush()
    assert len(j.state.chains) == 1 and j.rejected["InvalidMapError"] >= 1
