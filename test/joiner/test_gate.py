"""The χ² gate: known-answer NIS, consistent submaps pass, corrupted measurements are split off, config, CLI."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest
import scipy.stats

from linear_slam_ros.cli.main import main
from linear_slam_ros.core.errors import ConfigError
from linear_slam_ros.core.frames import change_frame
from linear_slam_ros.core.local_map import FEATURE, POSE, LocalMap
from linear_slam_ros.evaluation.synthetic import make_world, noisy_local_maps
from linear_slam_ros.joiner.config import JoinerConfig
from linear_slam_ros.joiner.joiner import Joiner, gate_step
from linear_slam_ros.joiner.strategy import JoinMethod
from linear_slam_ros.joining.divide_conquer import online_dc_result
from linear_slam_ros.joining.gate import Marginal, gate_submap, marginalise_out
from support import CACHE, dataset_archive, global_map_of


@pytest.fixture
def maps():
    world = make_world(2, 24, 20, np.random.default_rng(11))
    return noisy_local_maps(world, np.random.default_rng(12), steps_per_map=3)


def _feature_map(x: list[float], info: float, frame: int = 1) -> LocalMap:
    return LocalMap(2, frame, None, np.array([7]), np.array([FEATURE]), np.array(x), info * np.eye(2))


def test_known_answer_nis_on_an_exact_linear_case():
    marginal = Marginal(2, 1, np.array([7]), np.array([FEATURE], dtype=np.int8), np.array([1.0, 2.0]), 0.04 * np.eye(2))
    submap = _feature_map([1.3, 1.6], 100.0)  # r = (0.3, -0.4), P_S = 0.01 I: NIS = 0.25 / 0.05 = 5
    result = gate_submap(lambda keys: marginal, submap, 0.99)
    assert result.nis == pytest.approx(5.0) and result.dof == 2
    assert result.threshold == pytest.approx(scipy.stats.chi2.ppf(0.99, 2))
    assert result.passed and result.submap is submap
    failed = gate_submap(lambda keys: marginal, _feature_map([3.0, 2.0], 100.0), 0.99)  # NIS 4 / 0.05 = 80
    assert failed.nis == pytest.approx(80.0) and not failed.passed
    assert [(v.var_id, v.kind) for v in failed.split] == [(7, FEATURE)] and failed.submap is None


def test_marginalising_out_drops_a_block_diagonal_edge_exactly():
    ids, kinds = np.array([2, 3]), np.array([POSE, POSE])
    info = np.diag([1.0, 2.0, 3.0, 4.0, 5.0, 6.0])
    m = LocalMap(2, 1, 3, ids, kinds, np.arange(6.0), info)
    out = marginalise_out(m, [0])
    assert out.ids.tolist() == [3] and out.x.tolist() == [3.0, 4.0, 5.0]
    np.testing.assert_array_equal(out.info, np.diag([4.0, 5.0, 6.0]))


@pytest.mark.parametrize("mode", [JoinMethod.SEQUENTIAL, JoinMethod.ONLINE_DC])
def test_consistent_submaps_pass_and_the_map_is_unchanged(mode, maps):
    gated, plain = Joiner(mode, gate_probability=0.999999), Joiner(mode)
    for seq, m in enumerate(maps, start=1):
        assert gated.offer(m, seq) == [seq]
        plain.offer(m, seq)
    assert gated.gated == [] and gated.n_rejected == 0
    np.testing.assert_array_equal(global_map_of(gated.state).x, global_map_of(plain.state).x)


def test_online_dc_marginal_equals_the_merged_maps(maps):
    j = Joiner(JoinMethod.ONLINE_DC)
    for seq, m in enumerate(maps[:7], start=1):
        j.offer(m, seq)
    merged = online_dc_result(j.state.joined)
    keys = merged.keys[:6]
    fast = j.state.strategy.marginal(j.state.joined, keys)
    assert fast is not None
    exact = Marginal.of_map(change_frame(merged, fast.frame_id), keys)  # the same variables, in the same frame
    assert exact is not None
    order = [fast.keys.tolist().index(k) for k in exact.keys.tolist()]
    sizes = [3 if k == POSE else 2 for k in fast.kinds]
    starts = np.concatenate([[0], np.cumsum(sizes)])
    sc = np.concatenate([np.arange(starts[i], starts[i + 1]) for i in order])
    # the same linear LS folded oldest first instead of newest first: equal up to linearisation points (mm)
    np.testing.assert_allclose(fast.x[sc], exact.x, atol=5e-3)
    np.testing.assert_allclose(fast.cov[np.ix_(sc, sc)], exact.cov, rtol=0.05, atol=2e-4)


def _with_feature_moved(maps, shift=5.0):
    """The first submap (after the first) holding a feature already in the map, with that feature moved."""
    seen: set[int] = set()
    for k, m in enumerate(maps):
        common = [i for i, key in enumerate(m.keys.tolist()) if key in seen and m.kinds[i] == FEATURE]
        if k and common:
            i = common[0]
            x = m.x.copy()
            x[m.scalar_slice(i)] += shift
            return k, i, m.replace(x=x)
        seen.update(m.keys.tolist())
    raise AssertionError("no submap re-observes a feature")


@pytest.mark.parametrize("mode", [JoinMethod.SEQUENTIAL, JoinMethod.ONLINE_DC])
def test_a_corrupted_feature_is_split_off_and_the_rest_joined(mode, maps):
    k, i, bad = _with_feature_moved(maps)
    messages: list[tuple[str, str]] = []
    j = Joiner(mode, gate_probability=0.999999, on_reject=lambda r, msg: messages.append((r, msg)))
    ref = Joiner(mode)
    stream = [*maps[:k], bad, *maps[k + 1:]]
    clean = [*maps[:k], marginalise_out(maps[k], [i]), *maps[k + 1:]]
    for seq, (m, c) in enumerate(zip(stream, clean, strict=True), start=1):
        assert j.offer(m, seq) == [seq]
        ref.offer(c, seq)
    feature = int(maps[k].ids[i])
    assert [(g.submap, g.variables) for g in j.gated] == [(k + 1, (feature,))]
    assert j.rejected == {"gated": 1}
    reason, msg = messages[0]
    assert reason == "gated"
    assert re.search(rf"NIS [\d.]+ > χ² threshold [\d.]+ for \d+ dof .*worst: feature {feature} ", msg), msg
    np.testing.assert_allclose(global_map_of(j.state).x, global_map_of(ref.state).x, atol=1e-9)
    record = j.gated[0]  # the feature's own test is in the record, beside the submap's: the one that failed shows
    assert len(record.variable_nis) == len(record.variable_thresholds) == 1
    assert record.variable_nis[0] > record.variable_thresholds[0] > 0
    assert record.describe().startswith(f"seq {k + 1}: feature {feature} NIS {record.variable_nis[0]:.1f} > ")
    assert record.as_dict()["variable_nis"] == list(record.variable_nis) and record.as_dict()["robot"] == ""


def test_a_submap_left_with_nothing_leaves_the_map_unchanged(maps):
    j = Joiner(JoinMethod.ONLINE_DC, gate_probability=0.999999)
    for seq, m in enumerate(maps[:4], start=1):
        j.offer(m, seq)
    known = j.state.strategy.result(j.state.joined)
    f = int(np.flatnonzero(known.kinds == FEATURE)[0])
    fid, frame = int(known.ids[f]), int(known.frame_id)
    x = known.x[known.scalar_slice(f)] + 4.0
    lone = LocalMap(2, frame, frame, np.array([fid]), np.array([FEATURE]), x, 1e4 * np.eye(2))
    before = j.state
    assert gate_step(before, lone, 0.999999).submap is None
    assert j.offer(lone, 5) == []
    assert j.state.joined is before.joined and j.state.n_joined == before.n_joined
    assert j.rejected == {"gated": 1} and j.gated[0].rejected is False and j.gated[0].variables == (fid,)
    assert j.expected == 6  # its number is used: the stream goes on
    assert j.offer(maps[4], 6) == [6]


def test_config_errors_name_the_value():
    with pytest.raises(ConfigError, match=r"gate_probability=1\.5"):
        Joiner(JoinMethod.ONLINE_DC, gate_probability=1.5)
    with pytest.raises(ConfigError, match=r"gate_probability=2\.0 is outside its range"):
        JoinerConfig.from_mapping({"gate_probability": 2.0})
    with pytest.raises(ConfigError, match="gate_probability='high' must be of type float"):
        JoinerConfig.from_mapping({"gate_probability": "high"})
    assert JoinerConfig().gate_probability == 0.0


def test_cli_report_lists_the_gate_decisions(tmp_path, monkeypatch):
    monkeypatch.setenv("LINEAR_SLAM_CACHE", str(CACHE))
    archive = str(dataset_archive("8240_data_50_local_maps"))
    out = tmp_path / "gated"
    assert main(["join", archive, "--method", "online-dc", "--gate-probability", "0.999999", "--out", str(out)]) == 0
    report = json.loads((out / "report.json").read_text())
    assert report["gate_probability"] == 0.999999
    assert report["n_gated"] == len(report["gated"])
    assert report["n_reinitialised"] == len(report["reinitialised"])
    assert report["n_held"] == 0  # its submaps hold features and poses together: no closure to hold
    for g in report["gated"]:
        assert set(g) >= {"submap", "variables", "nis", "dof"}
    assert main(["join", archive, "--method", "dc", "--gate-probability", "0.99", "--out", str(tmp_path / "dc")]) == 2


def test_the_joiner_carries_the_variance_factor_and_its_gate_tightens_on_loose_information():
    """A stream whose information is 40 times too loose: the carried factor (once the tail calibration's
    confidence bound exists, from 90 fused submaps) tightens the gate enough to split off a feature moved by 2 m, which
    the gate at s² = 1 lets through; reset forgets the factor."""
    from dataclasses import replace

    from linear_slam_ros.evaluation.gating import global_keys
    from linear_slam_ros.joining.gate import VarianceFactor

    world = make_world(2, 1350, 40, np.random.default_rng(11), loops=5.0)  # 450 submaps: well past the bound's 90 fused ones
    clean = noisy_local_maps(world, np.random.default_rng(12), steps_per_map=3, sensor_range=5.0)
    loose = [m.replace(info=m.info / 40.0) for m in clean]
    j = Joiner(JoinMethod.ONLINE_DC, gate_probability=0.99999999)
    k = len(loose) - 2
    for seq, m in enumerate(loose[:k], start=1):
        assert j.offer(m, seq) == [seq]
    assert j.gated == []
    assert j.state.variance.dof > 1000 and j.state.variance.value < 0.2  # fused scalars; s² well below 1
    m = loose[k]
    known = global_keys(j.state)
    f = next(i for i in range(m.n_vars) if m.kinds[i] == FEATURE and int(m.keys[i]) in known)
    x = m.x.copy()
    x[m.scalar_slice(f).start] += 2.0
    bad = m.replace(x=x)
    untightened = gate_step(replace(j.state, variance=VarianceFactor(floor=1.0)), bad, 0.99999999)
    assert untightened.passed  # at s² >= 1 the 2 m move is within what the loose information allows
    before = j.state.variance
    assert j.offer(bad, k + 1) == [k + 1]
    assert [g.variables for g in j.gated] == [(int(m.ids[f]),)]
    assert j.state.variance.dof > before.dof  # the rest of the submap was fused and counted
    j.reset()
    assert j.state.variance == VarianceFactor()


def test_the_marginal_by_stack_entries_equals_the_prefix_merge_and_factorises_each_entry_once(maps, monkeypatch):
    import linear_slam_ros.joining.gate as gate_module
    from linear_slam_ros.core.local_map import pose_key
    from linear_slam_ros.joining.gate import EntryCache, PrefixCache, online_dc_marginal, online_dc_marginal_by_entries

    factorised: list[object] = []  # the matrices themselves: kept alive, their ids cannot be reused
    real = gate_module.spd_factor
    monkeypatch.setattr(gate_module, "spd_factor", lambda info: factorised.append(info) or real(info))
    j = Joiner(JoinMethod.ONLINE_DC)
    entries, prefixes = EntryCache(), PrefixCache()
    compared = 0
    for seq, m in enumerate(maps, start=1):
        if seq > 2:
            keys = np.concatenate([m.keys, [pose_key(m.frame_id)]])
            for _ in range(2):  # the second call asks nothing new: no factorisation, no solve
                by_entries = online_dc_marginal_by_entries(j.state.joined, keys, entries)
            merged = online_dc_marginal(j.state.joined, keys, prefixes)
            assert by_entries is not None and merged is not None
            assert by_entries.keys.tolist() == merged.keys.tolist() and by_entries.frame_id == merged.frame_id
            np.testing.assert_allclose(by_entries.x, merged.x, atol=1e-9)
            np.testing.assert_allclose(by_entries.cov, merged.cov, atol=1e-9 * np.abs(merged.cov).max())
            compared += 1
        j.offer(m, seq)
    assert compared >= 5
    assert len(factorised) == len({id(info) for info in factorised})  # each entry's information factorised once


def test_the_marginal_by_stack_entries_keeps_an_entry_frame_that_is_not_the_seam(read_benchmark):
    """Intel, before submap 744: the second stack entry is in the frame of pose 576, a variable of the
    first entry (a forward loop closure) but not its end pose (512); moving that entry to the seam makes
    pose 576 a variable of both. Dropping it from the first entry's reduction lost that link (the
    marginal's covariance was 29% off); both fast marginals now equal the prefix merge."""
    from linear_slam_ros.core.local_map import pose_key
    from linear_slam_ros.joining.divide_conquer import resolve
    from linear_slam_ros.joining.gate import online_dc_marginal, online_dc_marginal_by_entries

    maps = read_benchmark("Intel").maps
    j = Joiner(JoinMethod.ONLINE_DC)
    for seq, m in enumerate(maps[:743], start=1):
        j.offer(m, seq)
    first, second = (resolve(entry) for entry in j.state.joined.stack[:2])
    assert second.frame_id != first.end_id and first.has_pose(second.frame_id)
    keys = np.concatenate([maps[743].keys, [pose_key(maps[743].frame_id)]])
    by_entries = online_dc_marginal_by_entries(j.state.joined, keys)
    merged = online_dc_marginal(j.state.joined, keys)
    assert by_entries is not None and merged is not None
    np.testing.assert_allclose(by_entries.x, merged.x, atol=1e-9)
    np.testing.assert_allclose(by_entries.cov, merged.cov, atol=1e-9 * np.abs(merged.cov).max())


@pytest.mark.parametrize(
    ("counts", "merged"),
    [((), 0), ((1,), 0), ((2, 1), 1), ((4, 2, 1), 2), ((512, 256), 1), ((512, 128, 64, 32, 4, 2, 1), 3),
     ((2048, 1024, 256, 128, 32, 16, 8, 2), 3), ((8, 8, 8), 2)],
)
def test_the_big_prefix_is_the_oldest_entries_of_a_sixteenth_of_the_stream_or_more_never_the_top(counts, merged):
    from linear_slam_ros.joining.gate import big_prefix

    assert big_prefix(counts) == merged


def test_the_marginal_by_entries_merges_the_big_prefix_once_and_reuses_it(read_benchmark, monkeypatch):
    """Intel at 743 submaps (entries of 512, 128, 64, 32, 4, 2, 1): the three oldest are one part,
    merged and factorised once; the next submap's call (the same big entries) reuses both."""
    import linear_slam_ros.joining.gate as gate_module
    from linear_slam_ros.core.local_map import pose_key
    from linear_slam_ros.joining.gate import EntryCache, online_dc_marginal_by_entries

    maps = read_benchmark("Intel").maps
    j = Joiner(JoinMethod.ONLINE_DC)
    for seq, m in enumerate(maps[:743], start=1):
        j.offer(m, seq)
    assert j.state.joined.counts == (512, 128, 64, 32, 4, 2, 1)
    sizes: list[int] = []
    real = gate_module.spd_factor
    monkeypatch.setattr(gate_module, "spd_factor", lambda info: sizes.append(info.shape[0]) or real(info))
    cache = EntryCache()
    keys = np.concatenate([maps[743].keys, [pose_key(maps[743].frame_id)]])
    assert online_dc_marginal_by_entries(j.state.joined, keys, cache) is not None
    assert len(cache.entries(j.state.joined.stack, 3)) == 5
    merged_scalars = cache.entries(j.state.joined.stack, 3)[0].map.state_dim
    assert merged_scalars > 3 * 512 and merged_scalars in sizes  # the three big entries as one map, factorised
    j.offer(maps[743], 744)  # 744 = 512 + 128 + 64 + 32 + 8: the big entries stay
    before = len(sizes)
    keys = np.concatenate([maps[744].keys, [pose_key(maps[744].frame_id)]])
    assert online_dc_marginal_by_entries(j.state.joined, keys, cache) is not None
    assert merged_scalars not in sizes[before:]


def test_the_marginal_by_entries_folds_no_pending_merge_and_equals_the_merged_maps(monkeypatch):
    """Merges deferred and a few computed (the node's stack while its worker is busy): the marginal is
    taken from the pending joins' inputs, so the calling thread makes none of the joins the worker is
    making, and it equals the marginal of those parts joined in full."""
    import linear_slam_ros.joining.gate as gate_module
    from linear_slam_ros.core.local_map import pose_key
    from linear_slam_ros.joining.divide_conquer import (
        Deferred,
        OnlineDCState,
        leaf_entries,
        leaf_maps,
        online_dc_step,
        pending_joins,
    )
    from linear_slam_ros.joining.gate import PrefixCache, online_dc_marginal_by_entries

    rng = np.random.default_rng(5)
    maps = noisy_local_maps(make_world(2, 80, 60, rng, loops=2.0), rng, steps_per_map=2)
    state = OnlineDCState(defer_above=0)  # every merge deferred
    for i, m in enumerate(maps[:-1]):
        state = online_dc_step(state, m)
        if i % 7 == 6:  # some land, as a worker's would
            pending_joins(state.stack)[0].value()
    pending = pending_joins(state.stack)
    parts, counts = leaf_entries(state.stack, state.counts)
    assert pending and any(isinstance(p, Deferred) and p.done for p in parts)  # landed merges are parts whole
    assert [id(gate_module._entry_map(p)) for p in parts] == [id(m) for m in leaf_maps(state.stack)]
    assert sum(counts) == state.n_joined and len(parts) > len(state.stack)
    keys = np.concatenate([maps[-1].keys, [pose_key(maps[-1].frame_id)]])
    # the same parts joined one after the other, in full (a pending join's result, a tree of joins, differs
    # from that by linearisation: 6e-5 relative on this noisy stream, as the fold of its inputs did before)
    truth = Marginal.of_map(PrefixCache().merged(tuple(leaf_maps(state.stack))), keys)
    folded: list[object] = []
    real = gate_module._entry_map
    monkeypatch.setattr(gate_module, "_entry_map",
                        lambda e: (folded.append(e) if isinstance(e, Deferred) and not e.done else None) or real(e))
    fast = online_dc_marginal_by_entries(state, keys)
    assert not folded and not any(d.done for d in pending)
    assert fast is not None and truth is not None and fast.keys.tolist() == truth.keys.tolist()
    np.testing.assert_allclose(fast.x, truth.x, atol=1e-9)
    np.testing.assert_allclose(fast.cov, truth.cov, atol=1e-9 * np.abs(truth.cov).max())


@pytest.mark.parametrize("n_joined", [640, 743])
def test_both_fast_marginals_equal_the_marginal_of_the_merged_map(read_benchmark, monkeypatch, n_joined):
    """Intel at 640 submaps: the stack is [512, 128] and its top is in the frame of pose 576, which the
    prefix holds (a forward loop closure) but does not end at: the prefix path must keep that pose
    (it once did not). At 743 (seven entries) the entry path also marginalises out, after a join,
    what no later entry needs (the speed-up); both equal the marginal of the merged map itself."""
    import linear_slam_ros.joining.gate as gate_module
    from linear_slam_ros.core.local_map import pose_key
    from linear_slam_ros.joining.divide_conquer import resolve
    from linear_slam_ros.joining.gate import Marginal, PrefixCache, online_dc_marginal, online_dc_marginal_by_entries

    maps = read_benchmark("Intel").maps
    j = Joiner(JoinMethod.ONLINE_DC)
    for seq, m in enumerate(maps[:n_joined], start=1):
        j.offer(m, seq)
    stack = j.state.joined.stack
    if n_joined == 640:
        prefix, top = (resolve(entry) for entry in stack)
        assert top.frame_id != prefix.end_id and prefix.has_pose(top.frame_id)
    keys = np.concatenate([maps[n_joined].keys, [pose_key(maps[n_joined].frame_id)]])
    truth = Marginal.of_map(PrefixCache().merged(stack), keys)
    reduced: list[int] = []
    real = gate_module.marginalise_out
    monkeypatch.setattr(gate_module, "marginalise_out", lambda m, idx: reduced.append(len(idx)) or real(m, idx))
    for fast in (online_dc_marginal(j.state.joined, keys), online_dc_marginal_by_entries(j.state.joined, keys)):
        assert fast is not None and truth is not None
        assert fast.keys.tolist() == truth.keys.tolist() and fast.frame_id == truth.frame_id
        np.testing.assert_allclose(fast.x, truth.x, atol=1e-9)
        np.testing.assert_allclose(fast.cov, truth.cov, atol=1e-9 * np.abs(truth.cov).max())
    assert (sum(reduced) > 0) == (n_joined == 743)  # seven entries: variables done with are dropped on the way


def test_cli_join_refine_with_the_gate_refines_what_was_joined(tmp_path, monkeypatch):
    """``join --refine --gate-probability``: the refiner is given what the joins fused (the gate's splits left
    out), as the node's refiner is, and the report carries the gate's keys."""
    import linear_slam_ros.refinement.online as online
    from linear_slam_ros.io.datasets import read_dataset

    monkeypatch.setenv("LINEAR_SLAM_CACHE", str(CACHE))
    archive = dataset_archive("VicPark_200_local_maps")
    given: list[list[LocalMap]] = []
    real = online.refine_offline
    monkeypatch.setattr(online, "refine_offline", lambda maps, *a, **k: (given.append(list(maps)), real(maps, *a, **k))[1])
    out = tmp_path / "refined"
    assert main(["join", str(archive), "--method", "online-dc", "--gate-probability", "0.99999999", "--refine",
                 "--out", str(out)]) == 0
    report = json.loads((out / "report.json").read_text())
    (record,) = report["gated"]  # feature 34 of submap 17 (README, "Gating"): split off
    assert (record["submap"], record["variables"]) == (17, [34])
    assert report["n_gated"] == 1 and report["gate_probability"] == 0.99999999 and "n_held" in report
    maps = list(read_dataset(archive).maps)
    (measurements,) = given
    assert len(measurements) == len(maps)  # no forward closure held in VicPark200: one per submap
    k = record["submap"] - 1
    split = set(zip(record["variables"], record["kinds"], strict=True))
    kept = set(zip(measurements[k].ids.tolist(), measurements[k].kinds.tolist(), strict=True))
    assert split and not split & kept and kept < set(zip(maps[k].ids.tolist(), maps[k].kinds.tolist(), strict=True))
    assert all(np.array_equal(measurements[i].x, maps[i].x) and measurements[i].keys.tolist() == maps[i].keys.tolist()
               for i in range(len(maps)) if i != k)  # every other submap as it came


def test_the_gate_decides_alike_whether_or_not_the_background_merges_have_landed():
    """Each step is a function of (state, submap): with merges deferred (the node's default) the gate
    must not see whether the worker had finished one. Folded from a pending merge's inputs, the marginal
    was linearised in another grouping, and the NIS, s^2 in the state and so decisions depended on it."""
    rng = np.random.default_rng(5)
    maps = noisy_local_maps(make_world(2, 80, 60, rng, loops=2.0), rng, steps_per_map=2)[:60]
    runs = {}
    for name, defer in (("deferred, none landed", 0), ("synchronous", None)):
        j = Joiner(JoinMethod.ONLINE_DC, defer_above=defer, gate_probability=0.99999999)  # no worker: nothing lands
        for seq, m in enumerate(maps, start=1):
            j.offer(m, seq)
        runs[name] = j
    a, b = runs["deferred, none landed"], runs["synchronous"]
    assert a.state.variance.tail == b.state.variance.tail and a.state.variance.nis == b.state.variance.nis
    assert [(g.submap, g.variables, g.nis) for g in a.gated] == [(g.submap, g.variables, g.nis) for g in b.gated]
    assert global_map_of(a.state).x.tobytes() == global_map_of(b.state).x.tobytes()


def test_a_record_says_which_test_failed_when_the_submap_as_a_whole_passed():
    """VicPark200's submap 17 (a clean-data outlier, docs/gating.md) passes as a whole and fails on feature 34 alone:
    ``/diagnostics`` said "NIS 105.6 > 154.5", and report.json had no figure of the test that failed."""
    from linear_slam_ros.ros.bag_from_dataset import load_source
    from support import committed_bag

    bag = committed_bag("VicPark_200_local_maps")
    assert bag is not None
    j = Joiner(JoinMethod.ONLINE_DC, gate_probability=0.99999999)
    for seq, m in enumerate(load_source(bag).maps[:17], start=1):
        j.offer(m, seq)
    [record] = j.gated
    assert (record.submap, record.variables, record.dof, record.rejected) == (17, (34,), 60, False)
    assert record.nis <= record.threshold and record.variable_nis[0] > record.variable_thresholds[0]
    assert record.describe() == "seq 17: feature 34 NIS 64.4 > 45.4; submap NIS 105.6 <= 154.5 (60 dof)"


def test_a_record_names_the_robot_of_its_submap(maps):
    """Two robots' ``localmap_4`` could not be told apart in report.json's ``gated``."""
    k, i, bad = _with_feature_moved(maps)
    j = Joiner(JoinMethod.ONLINE_DC, gate_probability=0.999999)
    for seq, m in enumerate([*maps[:k], bad], start=1):
        j.offer(m, seq, "b")
    [record] = j.gated
    assert record.robot == "b" and record.as_dict()["robot"] == "b"
    assert record.describe().startswith(f"robot b seq {k + 1}: feature {int(maps[k].ids[i])} NIS ")
