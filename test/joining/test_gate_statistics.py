"""The χ² gate's statistics: the per-variable (Šidák) test, the variance of unit weight, NIS = objective increase."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.stats

from linear_slam_ros.core.errors import ConfigError
from linear_slam_ros.core.local_map import FEATURE, LocalMap
from linear_slam_ros.evaluation.gating import corrupt, position_rms
from linear_slam_ros.evaluation.objective import chi2
from linear_slam_ros.evaluation.synthetic import make_world, noisy_local_maps
from linear_slam_ros.joiner.joiner import Joiner
from linear_slam_ros.joiner.strategy import JoinMethod
from linear_slam_ros.joining.gate import (
    PRIOR_DOF,
    TAIL_CONFIDENCE,
    TAIL_QUANTILE,
    GateResult,
    Marginal,
    VarianceFactor,
    gate_submap,
    tail_order_statistic,
)
from linear_slam_ros.joining.pairwise import join_pair

N_FEATURES = 20


def _features(x: np.ndarray, cov: float) -> Marginal:
    ids = np.arange(1, N_FEATURES + 1)
    return Marginal(2, 0, ids, np.full(N_FEATURES, FEATURE, dtype=np.int8), x, cov * np.eye(2 * N_FEATURES))


def _submap(x: np.ndarray, info: float) -> LocalMap:
    ids = np.arange(1, N_FEATURES + 1)
    return LocalMap(2, 0, None, ids, np.full(N_FEATURES, FEATURE), x, info * np.eye(2 * N_FEATURES))


def test_one_wrong_variable_among_many_is_split_off_though_the_total_passes():
    # innovation covariance 0.05 I per scalar; feature 7 off by 1.5 m along x: its NIS 45 (2 dof)
    x = np.zeros(2 * N_FEATURES)
    moved = x.copy()
    moved[12] = 1.5
    result = gate_submap(lambda keys: _features(x, 0.04), _submap(moved, 100.0), 0.999999)
    assert result.nis == pytest.approx(45.0) and result.dof == 2 * N_FEATURES
    assert result.nis < result.threshold == pytest.approx(scipy.stats.chi2.ppf(0.999999, 2 * N_FEATURES))
    sidak = scipy.stats.chi2.ppf(0.999999 ** (1 / N_FEATURES), 2)
    assert result.variable_threshold == pytest.approx(sidak) and result.n_common == N_FEATURES
    assert [(v.var_id, v.kind) for v in result.split] == [(7, FEATURE)] and not result.rejected
    assert result.submap is not None and 7 not in result.submap.ids.tolist() and result.dof_after == result.dof - 2


def test_the_variance_factor_scales_the_thresholds():
    # every feature off by 0.4 m along x: NIS 3.2 per 2 dof, 64 for 40 (nominal threshold 83; at p 0.9: 51)
    x = np.zeros(2 * N_FEATURES)
    off = x.copy()
    off[0::2] = 0.4
    nominal = gate_submap(lambda keys: _features(x, 0.04), _submap(off, 100.0), 0.9)
    assert nominal.nis == pytest.approx(64.0) and nominal.rejected and nominal.variance_factor == 1.0
    scaled = VarianceFactor(nis=4.0 * 1000, dof=1000)
    assert scaled.value == pytest.approx((PRIOR_DOF + 4000.0) / (PRIOR_DOF + 1000.0))
    passed = gate_submap(lambda keys: _features(x, 0.04), _submap(off, 100.0), 0.9, scaled)
    assert passed.passed and passed.variance_factor == pytest.approx(scaled.value)
    assert passed.threshold == pytest.approx(scaled.value * 40 * scipy.stats.f.ppf(0.9, 40, scaled.nu))


def test_variance_factor_estimate_floor_and_limits():
    assert VarianceFactor.nominal().threshold(0.99, 3) == pytest.approx(scipy.stats.chi2.ppf(0.99, 3))
    # a long χ²-consistent stream at scale 0.25 (information 4 times too loose): both estimates find it
    rng = np.random.default_rng(5)
    k = rng.integers(2, 7, size=2000)
    nis = 0.25 * rng.chisquare(k)
    u = tuple(float(x) for x in nis / scipy.stats.chi2.ppf(TAIL_QUANTILE, k))
    loose = VarianceFactor(nis=float(nis.sum()), dof=float(k.sum()), tail=u)
    assert loose.mean == pytest.approx(0.25, rel=0.05) and loose.tail_scale == pytest.approx(0.25, rel=0.1)
    assert loose.value == max(loose.mean, loose.tail_scale) < 0.3
    assert VarianceFactor(nis=loose.nis, dof=loose.dof, tail=u, floor=1.0).value == 1.0  # the gate that never tightens
    # heavy tails (a tenth of the submaps at scale 4, the rest at 0.05: mean 0.45): the tail keeps the scale up
    heavy = tuple(float(x) for x in np.where(rng.random(2000) < 0.1, 16.0, 0.2) * np.asarray(u))
    assert VarianceFactor(nis=loose.nis, dof=loose.dof, tail=heavy).tail_scale > 1.0
    # before the bound exists (89 fused submaps at 0.99), twice the largest u, at most 1
    early = (0.01,) * 88 + (0.1,)
    assert VarianceFactor(nis=0.0, dof=300.0, tail=early).tail_scale == pytest.approx(0.2)
    assert VarianceFactor(nis=0.0, dof=300.0, tail=(*early[:-1], 0.7)).tail_scale == 1.0
    assert VarianceFactor(nis=0.0, dof=300.0, tail=(*early[:-1], 0.7)).value == 1.0
    # from 90 on, the order statistic: the largest of 90, then of 100 the 100th, of 470 the 458th
    assert VarianceFactor(nis=0.0, dof=300.0, tail=(*early, 0.05)).tail_scale == 0.1
    spread = tuple(float(x) for x in rng.permutation(np.arange(1, 471) / 1000.0))
    assert VarianceFactor(nis=0.0, dof=3000.0, tail=spread).tail_scale == pytest.approx(0.458)
    assert VarianceFactor(nis=0.0, dof=3000.0, tail=spread[:100]).tail_scale == max(spread[:100])
    assert VarianceFactor().tail_scale == 1.0 and VarianceFactor().value == 1.0
    few = VarianceFactor(nis=5.0, dof=5.0, tail=(1.0,))  # F quantile: a short stream's thresholds stay wide
    assert few.threshold(0.999, 3) > scipy.stats.chi2.ppf(0.999, 3)
    few, many = VarianceFactor(nis=5.0, dof=5.0), VarianceFactor(nis=1e6, dof=1e6)
    chi2_q = scipy.stats.chi2.ppf(0.999, 4)
    assert few.threshold(0.999, 4) > many.threshold(0.999, 4) > chi2_q  # F quantile: wider while ν is small
    assert many.threshold(0.999, 4) == pytest.approx(chi2_q, rel=1e-2)
    assert few.threshold(0.999, 0) == float("inf")
    passed = GateResult(0.9, 8.0, 4, 9.0, nis_after=8.0, dof_after=4)
    rejected = GateResult(0.9, 80.0, 4, 9.0, nis_after=0.0, dof_after=4, rejected=True)
    u = 8.0 / scipy.stats.chi2.ppf(TAIL_QUANTILE, 4)
    assert few.updated(passed) == VarianceFactor(nis=13.0, dof=9.0, tail=(u,)) and few.updated(rejected) is few


def test_tail_order_statistic_is_the_binomial_bound():
    for n in (90, 100, 470, 3000):
        k = tail_order_statistic(n, TAIL_QUANTILE, TAIL_CONFIDENCE)
        assert scipy.stats.binom.cdf(k - 1, n, TAIL_QUANTILE) >= TAIL_CONFIDENCE
        assert k == 1 or scipy.stats.binom.cdf(k - 2, n, TAIL_QUANTILE) < TAIL_CONFIDENCE
    assert [tail_order_statistic(n, TAIL_QUANTILE, TAIL_CONFIDENCE) for n in (0, 1, 89, 90, 100, 470)] == [
        None, None, None, 90, 100, 458]
    assert tail_order_statistic(10, 0.5, 0.9) == 8  # P(Bin(10, 1/2) <= 7) = 0.945, <= 6: 0.828


@pytest.mark.parametrize(("quantile", "confidence", "match"), [
    (1.0, 0.99, r"quantile=1.0 must be in \(0, 1\)"), (0.95, 0.0, r"confidence=0.0 must be in \(0, 1\)"),
    (float("nan"), 0.99, r"quantile=nan must be in \(0, 1\)"),
])
def test_tail_order_statistic_refuses_probabilities_outside_zero_one(quantile, confidence, match):
    with pytest.raises(ConfigError, match=match):
        tail_order_statistic(100, quantile, confidence)


@pytest.mark.parametrize(("field", "value", "match"), [
    ("nis", -1.0, r"VarianceFactor.nis=-1.0 must be"), ("dof", float("nan"), r"VarianceFactor.dof=nan must be"),
    ("prior_dof", -2.0, r"VarianceFactor.prior_dof=-2.0 must be"),
    ("tail_confidence", 1.0, r"VarianceFactor.tail_confidence=1.0 must be in \(0, 1\)"),
    ("tail", (0.5, float("nan")), r"VarianceFactor.tail\[1\]=nan must be a finite number >= 0"),
    ("tail", (-0.1,), r"VarianceFactor.tail\[0\]=-0.1 must be a finite number >= 0"),
])
def test_variance_factor_errors_name_the_value(field, value, match):
    with pytest.raises(ConfigError, match=match):
        VarianceFactor(**{field: value})
    with pytest.raises(ConfigError, match=r"prior_dof=0.0 \+ dof=0.0 must be > 0"):
        VarianceFactor(prior_dof=0.0)


@pytest.mark.parametrize("probability", [0.0, 1.0, 1.5])
def test_gate_probability_out_of_range_is_named(probability):
    x = np.zeros(2 * N_FEATURES)
    with pytest.raises(ConfigError, match=rf"gate probability={probability!r} must be in \(0, 1\)"):
        gate_submap(lambda keys: _features(x, 0.04), _submap(x, 100.0), probability)


def test_nis_is_the_objective_increase_of_the_join_in_another_frame():
    """The gate's NIS (map marginal moved into the submap's frame, frame pose and correlations included)
    equals the χ² of joining the marginal with the submap, evaluated by the nonlinear objective."""
    world = make_world(2, 24, 20, np.random.default_rng(11))
    maps = noisy_local_maps(world, np.random.default_rng(12), steps_per_map=3)
    j = Joiner(JoinMethod.ONLINE_DC)
    checked = 0
    for seq, m in enumerate(maps, start=1):
        if seq > 2:
            marginal = j.state.strategy.marginal(j.state.joined, np.concatenate([m.keys, [2 * m.frame_id]]))
            assert marginal is not None
            result = gate_submap(lambda keys, mg=marginal: mg, m, 0.999999)
            if result.dof and marginal.frame_id != m.frame_id:
                small = marginal.to_local_map().replace(end_id=m.frame_id)
                both = chi2(join_pair(small, m), [small, m])
                assert result.nis == pytest.approx(both, rel=1e-2, abs=1e-6)  # linear vs nonlinear: 0.4%
                checked += 1
        j.offer(m, seq)
    assert checked >= 3


def test_corruption_model_and_position_rms():
    world = make_world(2, 24, 20, np.random.default_rng(11))
    m = noisy_local_maps(world, np.random.default_rng(12), steps_per_map=3)[3]
    f = int(np.flatnonzero(m.kinds == FEATURE)[0])
    bad = corrupt(m, f, np.random.default_rng(0))
    moved = np.linalg.norm(bad.x[m.scalar_slice(f)] - m.x[m.scalar_slice(f)])
    assert 2.0 <= moved <= 5.0
    assert np.array_equal(np.delete(bad.x, np.r_[m.scalar_slice(f)]), np.delete(m.x, np.r_[m.scalar_slice(f)]))
    assert position_rms(bad, m) == pytest.approx(moved / np.sqrt(m.n_vars))


def test_clean_pass_gates_nothing_on_consistent_data_and_trials_pick_loop_closures():
    from linear_slam_ros.evaluation.gating import _common_vars, clean_pass, global_keys

    world = make_world(2, 24, 20, np.random.default_rng(11))
    maps = noisy_local_maps(world, np.random.default_rng(12), steps_per_map=3)[:12]
    clean = clean_pass(maps, 0.99999999)
    assert clean.gated == [] and int(clean.dof.sum()) > 0
    assert np.array_equal(clean.final.x, clean.plain_final.x)  # nothing gated: the ungated map, bit for bit
    assert clean.variances[-1].dof == pytest.approx(float(clean.dof[:-1].sum()))
    for k in range(1, len(maps)):
        common = _common_vars(clean.states[k], maps[k])
        known = global_keys(clean.states[k])
        assert all(int(maps[k].keys[i]) in known for i in common)
        assert all(not (maps[k].kinds[i] != FEATURE and maps[k].ids[i] == maps[k].end_id) for i in common)


def test_the_gates_chi2_and_f_functions_give_scipy_stats_numbers():
    """The gate calls scipy.special (scipy.stats costs the node ~30 MB); the numbers are scipy.stats's, bit for bit."""
    from linear_slam_ros.joining.gate import chi2_ppf, chi2_threshold

    for dof in (1, 2, 3, 6, 9, 30, 300, 3000):
        for p in (0.0, 0.5, 0.95, 0.99999999, 1.0):
            assert chi2_ppf(p, dof) == float(scipy.stats.chi2.ppf(p, dof))
        assert chi2_threshold(0.9999, dof) == float(scipy.stats.chi2.ppf(0.9999, dof))
        for x in (-1e-16, 0.0, 1e-3, 0.5, 5.0, 50.0, 1722.0, 1e6, np.inf):
            assert VarianceFactor(prior_dof=np.inf).logsf(x, dof) == float(scipy.stats.chi2.logsf(x, dof))
            scale = VarianceFactor(nis=30.0, dof=100.0)  # s² and ν from data: the F distribution
            assert scale.logsf(x, dof) == float(scipy.stats.f.logsf(x / (scale.value * dof), dof, scale.nu))
        assert scale.threshold(0.9999, dof) == scale.value * dof * float(scipy.stats.f.ppf(0.9999, dof, scale.nu))
    assert chi2_threshold(0.9999, 0) == float("inf")
