"""Deferred merges of online divide and conquer and the background worker that computes them."""

from __future__ import annotations

import threading
import weakref

import numpy as np
import pytest
import scipy.sparse as sp

from linear_slam_ros.core.errors import FrameError
from linear_slam_ros.core.local_map import LocalMap
from linear_slam_ros.evaluation.synthetic import exact_pose_graph_maps, make_world, noisy_local_maps
from linear_slam_ros.joining import divide_conquer
from linear_slam_ros.joining.background import MergeWorker
from linear_slam_ros.joining.chain import chain_end_pose
from linear_slam_ros.joining.divide_conquer import (
    Deferred,
    OnlineDCState,
    StackChain,
    leaf_maps,
    online_dc_result,
    online_dc_step,
    pending_joins,
)


def _assert_same_map(a: LocalMap, b: LocalMap) -> None:
    """Bit for bit: the same variables, estimate and information."""
    assert (a.frame_id, a.end_id) == (b.frame_id, b.end_id)
    np.testing.assert_array_equal(a.ids, b.ids)
    np.testing.assert_array_equal(a.kinds, b.kinds)
    np.testing.assert_array_equal(a.x, b.x)
    info_a = a.info.toarray() if sp.issparse(a.info) else a.info
    info_b = b.info.toarray() if sp.issparse(b.info) else b.info
    np.testing.assert_array_equal(info_a, info_b)


def _run(maps: list[LocalMap], defer_above: int | None, worker: MergeWorker | None = None) -> OnlineDCState:
    state = OnlineDCState(defer_above=defer_above)
    for m in maps:
        state = online_dc_step(state, m)
        if worker is not None:
            worker.submit(pending_joins(state.stack))
    return state


@pytest.fixture
def maps(rng: np.random.Generator) -> list[LocalMap]:
    return noisy_local_maps(make_world(2, 80, 60, rng, loops=2.0), rng, steps_per_map=2)


@pytest.fixture
def worker():
    w = MergeWorker()
    yield w
    w.stop()
    assert not w.alive


def test_deferred_merges_give_the_synchronous_map_bit_for_bit(maps, worker):
    sync = _run(maps, None)
    assert not any(isinstance(e, Deferred) for e in sync.stack)
    for defer_above in (0, 40):
        lazy = _run(maps, defer_above)  # nobody computes ahead: the result computes every deferred merge
        assert any(isinstance(e, Deferred) and not e.done for e in lazy.stack)
        _assert_same_map(online_dc_result(lazy), online_dc_result(sync))
    ahead = _run(maps, 0, worker)
    assert worker.wait_idle(60.0) and worker.n_done > 0
    assert pending_joins(ahead.stack) == []
    assert ahead.counts == sync.counts and ahead.n_joined == sync.n_joined == len(maps)
    _assert_same_map(online_dc_result(ahead), online_dc_result(sync))


def test_pending_joins_list_inputs_before_results(maps):
    state = _run(maps[:8], 0)  # 8 submaps, every merge deferred: 1+1, 1+1, 2+2, ..., 4+4
    order = pending_joins(state.stack)
    assert len(order) == 7 and order[-1] is state.stack[0]
    position = {id(d): i for i, d in enumerate(order)}
    for d in order:
        for parent_input in d.inputs or ():
            if isinstance(parent_input, Deferred):
                assert position[id(parent_input)] < position[id(d)]


def test_a_merge_finishes_while_arrivals_go_on(maps, monkeypatch, worker):
    """The worker holds a large merge; arrivals keep being joined meanwhile, then the merge lands."""
    release, started = threading.Event(), threading.Event()
    real_join = divide_conquer.join_at_seam

    def slow_in_worker(a, b, name="global"):
        if threading.current_thread().name == "linear_slam_merge":
            started.set()
            assert release.wait(30.0)
        return real_join(a, b, name)

    monkeypatch.setattr(divide_conquer, "join_at_seam", slow_in_worker)
    halves = [_run(maps[i : i + 4], None).stack[0].state_dim for i in (0, 4)]
    quarters = [_run(maps[i : i + 2], None).stack[0].state_dim for i in range(0, 14, 2)]
    big = sum(halves) - 1  # two 4-submap halves merge above this; smaller merges do not
    assert max(a + b for a, b in zip(quarters[::2], quarters[1::2], strict=False)) <= big
    state = OnlineDCState(defer_above=big)
    for m in maps[:8]:
        state = online_dc_step(state, m)
        worker.submit(pending_joins(state.stack))
    assert started.wait(30.0)
    merging = state.stack[0]
    assert isinstance(merging, Deferred) and not merging.done and state.counts == (8,)
    for m in maps[8:14]:  # arrivals while the merge of the first 8 is held in the worker
        state = online_dc_step(state, m)
    assert not merging.done and state.counts == (8, 4, 2)
    assert not any(isinstance(e, Deferred) for e in state.stack[1:])  # the small levels joined on arrival
    release.set()
    assert worker.wait_idle(30.0) and merging.done
    state = online_dc_step(state, maps[14])
    assert not isinstance(state.stack[0], Deferred)  # the computed merge replaced its description
    monkeypatch.setattr(divide_conquer, "join_at_seam", real_join)
    _assert_same_map(online_dc_result(state), online_dc_result(_run(maps[:15], None)))


def test_stop_during_a_merge_leaves_no_thread(maps, monkeypatch):
    release, started = threading.Event(), threading.Event()
    real_join = divide_conquer.join_at_seam

    def held(a, b, name="global"):
        started.set()
        assert release.wait(30.0)
        return real_join(a, b, name)

    worker = MergeWorker()
    monkeypatch.setattr(divide_conquer, "join_at_seam", held)
    state = _run(maps[:16], 0, worker)
    assert started.wait(30.0)
    stopper = threading.Thread(target=worker.stop)
    stopper.start()
    release.set()  # the merge under way finishes; the queued ones are dropped
    stopper.join(30.0)
    assert not stopper.is_alive() and not worker.alive
    assert worker.n_done <= 1 and pending_joins(state.stack)  # the rest was left for whoever needs it
    monkeypatch.setattr(divide_conquer, "join_at_seam", real_join)
    _assert_same_map(online_dc_result(state), online_dc_result(_run(maps[:16], None)))


def test_clear_drops_queued_merges(maps, monkeypatch):
    release = threading.Event()
    real_join = divide_conquer.join_at_seam
    monkeypatch.setattr(divide_conquer, "join_at_seam", lambda a, b, name="global": (release.wait(30.0), real_join(a, b))[1])
    worker = MergeWorker()
    try:
        _run(maps[:16], 0, worker)
        worker.clear()
        release.set()
        assert worker.wait_idle(30.0)
        assert worker.n_done <= 1  # at most the one under way when cleared
    finally:
        worker.stop()


def test_a_failing_deferred_merge_raises_to_whoever_asks(maps):
    state = _run(maps[:2], 0)
    merge = state.stack[0]
    assert isinstance(merge, Deferred)
    bad = maps[1].replace(frame_id=999_999, ids=maps[1].ids + 1_000_000)  # shares no pose with maps[0]
    broken = Deferred(maps[0], bad, 2)
    worker = MergeWorker()
    try:
        worker.submit([broken])
        assert worker.wait_idle(30.0) and not broken.done
    finally:
        worker.stop()
    with pytest.raises(FrameError, match="does not hold pose"):
        broken.value()


def test_a_failed_deferred_merge_is_not_computed_again(maps, monkeypatch):
    """A failed merge was submitted again at every arrival and made again at every publication: 235 attempts
    over 88 arrivals (a review of session 26). The same inputs fail the same way: the error is kept."""
    bad = maps[1].replace(frame_id=999_999, ids=maps[1].ids + 1_000_000)  # shares no pose with maps[0]
    broken = Deferred(maps[0], bad, 2)
    above = Deferred(broken, maps[2], 3)
    calls = []
    real_join = divide_conquer.join_at_seam
    monkeypatch.setattr(divide_conquer, "join_at_seam", lambda a, b, name="global": (calls.append(1), real_join(a, b))[1])
    worker = MergeWorker()
    try:
        worker.submit(pending_joins([above]))
        assert worker.wait_idle(30.0) and broken.failed and above.failed and len(calls) == 1
        assert pending_joins([above]) == []
        worker.submit([broken, above])  # not queued again
        assert worker.wait_idle(30.0) and len(calls) == 1
    finally:
        worker.stop()
    for d in (broken, above):
        with pytest.raises(FrameError, match="does not hold pose"):
            d.value()
    assert len(calls) == 1


def test_chained_pose_is_the_end_pose_of_the_merged_map_for_exact_maps(rng):
    """Noise-free maps agree, so chaining the parts gives the merged map's end pose exactly."""
    world = make_world(2, 40, 0, rng)
    maps = exact_pose_graph_maps(world, rng)
    state = _run(maps, 0)
    parts = leaf_maps(state.stack)
    assert len(parts) == len(maps)  # nothing computed: every submap is a part
    end_id, pose = chain_end_pose(parts, maps[0].frame_id)
    merged = online_dc_result(state)
    assert end_id == merged.end_id
    np.testing.assert_allclose(pose, world.poses[end_id], atol=1e-9)
    assert chain_end_pose([], 0) is None
    assert chain_end_pose([maps[3]], maps[0].frame_id) is None  # does not hold the frame pose


@pytest.mark.parametrize("dim", [2, 3])
def test_the_stack_chain_equals_chaining_the_leaves_as_merges_land(dim, rng):
    """StackChain (the node's fresh pose) gives chain_end_pose over the leaves, step after step, while
    deferred merges stay pending or land in any order."""
    world = make_world(dim, 70, 40, rng, loops=2.0)  # shared features: a merge moves its parts' poses
    maps = noisy_local_maps(world, rng, steps_per_map=2)
    chain = StackChain()
    state = OnlineDCState(defer_above=0)  # every merge deferred: a deep pending tree
    landed, moved = 0, 0.0
    for i, m in enumerate(maps):
        state = online_dc_step(state, m)
        if i % 5 == 4:  # a merge lands somewhere in the pending tree (not necessarily the oldest)
            pending = pending_joins(state.stack)
            before = chain_end_pose(leaf_maps(state.stack), maps[0].frame_id)
            pending[int(rng.integers(len(pending)))].value()
            after = chain_end_pose(leaf_maps(state.stack), maps[0].frame_id)
            moved = max(moved, float(np.abs(after[1] - before[1]).max()))
            landed += 1
        expected = chain_end_pose(leaf_maps(state.stack), maps[0].frame_id)
        got = chain.end_pose(state.stack, maps[0].frame_id)
        assert got is not None and expected is not None and got[0] == expected[0]
        np.testing.assert_allclose(got[1], expected[1], rtol=0, atol=1e-9)
    assert landed > 3 and any(isinstance(e, Deferred) and not e.done for e in state.stack)
    assert moved > 1e-6  # the landed merges changed the chained pose: a stale composition would show
    assert chain.end_pose((), 0) is None
    assert chain.end_pose(state.stack, maps[3].frame_id + 10_000) is None  # the first part does not hold it


def test_the_stack_chain_recomposes_only_what_changed(rng, monkeypatch):
    world = make_world(3, 70, 0, rng, loops=2.0)
    maps = noisy_local_maps(world, rng, steps_per_map=2)
    state = _run(maps, 0)  # 34 submaps, every merge pending
    calls = {"relative_end": 0, "compose": 0}

    def counted(name, real):
        def wrapper(*args):
            calls[name] += 1
            return real(*args)

        return wrapper

    monkeypatch.setattr(divide_conquer, "relative_end", counted("relative_end", divide_conquer.relative_end))
    monkeypatch.setattr(divide_conquer, "compose", counted("compose", divide_conquer.compose))
    chain = StackChain()
    first = chain.end_pose(state.stack, maps[0].frame_id)
    assert calls["relative_end"] == len(leaf_maps(state.stack)) == len(maps)
    calls.update(relative_end=0, compose=0)
    assert chain.end_pose(state.stack, maps[0].frame_id) is first  # nothing changed: nothing recomputed
    assert calls == {"relative_end": 0, "compose": 0}
    pending = pending_joins(state.stack)
    deepest = pending[0]  # inputs before results: a join of two submaps, at the bottom of the tree
    deepest.value()
    again = chain.end_pose(state.stack, maps[0].frame_id)
    assert calls["relative_end"] == 1  # the landed merge's own relative pose, and nothing else's
    assert 0 < calls["compose"] <= 2 * len(pending)  # along the path above it and the stack: not every leaf after it
    expected = chain_end_pose(leaf_maps(state.stack), maps[0].frame_id)
    np.testing.assert_allclose(again[1], expected[1], rtol=0, atol=1e-9)


def test_the_stack_chain_lets_a_landed_merges_inputs_go(rng):
    """A merge that lands releases its inputs (peak memory): the chain's cache must not keep them."""
    world = make_world(2, 40, 0, rng)
    maps = exact_pose_graph_maps(world, rng)
    state = _run(maps, 0)
    chain = StackChain()
    assert chain.end_pose(state.stack, maps[0].frame_id) is not None
    oldest = state.stack[0]
    assert isinstance(oldest, Deferred) and oldest.inputs is not None
    assert all(isinstance(e, Deferred) for e in oldest.inputs)  # joins of joins: only the cache holds them besides
    inputs = [weakref.ref(e) for e in oldest.inputs]
    oldest.value()
    assert [r() for r in inputs] == [None, None]
    merged = chain_end_pose(leaf_maps(state.stack), maps[0].frame_id)
    np.testing.assert_allclose(chain.end_pose(state.stack, maps[0].frame_id)[1], merged[1], rtol=0, atol=1e-9)


def test_the_worker_survives_an_unexpected_error_and_counts_only_its_own_merges(maps, monkeypatch, caplog):
    """A MemoryError of one large merge ended the worker thread for good, and its queue then held every
    deferred merge of the stream (review of session 26); merges another thread made were counted as its own."""
    import time

    real_join = divide_conquer.join_at_seam
    failed: list[bool] = []
    in_worker = [0]

    def join(a, b, name="global"):
        if not failed:
            failed.append(True)
            raise MemoryError("a large merge")
        if threading.current_thread().name == "linear_slam_merge":
            in_worker[0] += 1
            time.sleep(0.02)  # slow: the thread asking for the result makes most of the queued merges itself
        return real_join(a, b, name)

    monkeypatch.setattr(divide_conquer, "join_at_seam", join)
    worker = MergeWorker()
    try:
        state = _run(maps[:16], 0, worker)
        assert worker.wait_idle(30.0) and worker.alive
        assert "deferred join failed unexpectedly" in caplog.text and "MemoryError: a large merge" in caplog.text
        _assert_same_map(online_dc_result(state), online_dc_result(_run(maps[:16], None)))  # computed again on demand
        lazy = _run(maps[:32], 0)
        pending = pending_joins(lazy.stack)
        worker.submit(pending)
        online_dc_result(lazy)  # this thread makes what the slow worker has not
        assert worker.wait_idle(30.0)
        assert worker.n_done == in_worker[0] and in_worker[0] < len(pending) + 15
    finally:
        worker.stop()
