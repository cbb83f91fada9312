"""Seeded benchmark of the χ² gate (issue 11, part 3): detection of one corrupted measurement, false positives.

Run as ``python -m linear_slam_ros.evaluation.gating --datasets-dir ../shared/datasets --out out/benchmark``;
writes ``gating.md`` and ``gating.json``.

Per dataset, the clean stream is joined once by online D&C with the gate applied before every
submap (as the node does, the stream's variance factor :class:`VarianceFactor` carried along): the
submaps it gates on clean data are false alarms, and the final map's χ² is compared with the
ungated run's (bit-identical when nothing is gated). The NIS of each clean submap also gives the
fraction the gate would touch at other probabilities (evaluated, not applied). The states before
each submap are kept (immutable values). ``--clean-only`` datasets get this clean check alone.

Forward loop closures are held back until the chain reaches their pose, as the joiner does with
the gate on (:mod:`~linear_slam_ros.joining.hold`; ``--no-hold``: fused on arrival, untested), in
the gated and the ungated runs alike; the clean check also gives the ungated run without holding.

Corruption model, one per trial (seeded ``numpy.random.default_rng(seed + trial)``): a random submap
``k`` that holds a variable already in the map, or a forward loop closure the gate tested when the
chain reached its pose; one such variable ``v`` is moved in the submap's estimate (its information
unchanged): a pose by 1–3 m in a random direction and 15–45° (random sign; the yaw ``alpha`` in 3D),
a feature by 2–5 m in a random direction. The corrupted submap is gated against the clean state
before ``k`` (with the variance factor of that point); a held closure is gated when the chain
reaches its pose (the submaps in between joined without the gate, the clean pass's variance factor
at that point). *Detected*: ``v`` is among the variables gated (split off, or the submap gated
whole). Map error: the final map of the gated stream against the clean stream with ``v``
marginalised out of submap ``k`` ("the clean run without that measurement"), RMS of the position
error of every pose and feature in the frame of the first pose. When the two states are the same
bit for bit once ``v`` has been decided on (``v`` alone split off), the rest of both streams is the
same and the error is 0 exactly; only the other trials are re-run to the end (both streams, the
rest joined without the gate).
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
import scipy.sparse as sp

from linear_slam_ros.core.errors import LinearSlamError
from linear_slam_ros.core.frames import change_frame
from linear_slam_ros.core.local_map import FEATURE, POSE, LocalMap, pose_key
from linear_slam_ros.evaluation.objective import chi2
from linear_slam_ros.io.datasets import read_dataset
from linear_slam_ros.joiner.joiner import JoinerState, SubmapStep, global_result, new_state, submap_step
from linear_slam_ros.joiner.strategy import JoinMethod
from linear_slam_ros.joining.divide_conquer import leaf_maps
from linear_slam_ros.joining.gate import GateResult, VarianceFactor, marginalise_out
from linear_slam_ros.joining.hold import HeldClosure
from linear_slam_ros.joining.reinit import Reinitialisation, as_joined

logger = logging.getLogger(__name__)

DATASETS = ("VicPark_200_local_maps", "DLR_200_local_maps", "Intel", "manhattanOlson3500", "sphere2500")
CLEAN_ONLY = ("8240_data_50_local_maps", "Simu_3D_870_Loop", "VicPark_6898_local_maps")
"""The other datasets of ``shared/datasets``: the clean check only (no corruption trials)."""
PROBABILITY = 0.99999999
"""Gate probability of the benchmark (and the documented recommendation): 1 - 1e-8, see the README's gating
section and docs/gating.md."""
PROBABILITIES = (0.9999, 0.999999, 0.99999999, 1.0 - 1e-12)


@dataclass(frozen=True)
class CleanPass:
    """The clean stream with the gate applied before each submap.

    Attributes:
        states: the joiner state before each submap (``states[k]`` before ``maps[k]``).
        variances: the variance factor before each submap.
        results: the gate decision on each submap (against the map before it; dof 0: nothing in common).
        gate_ms: wall time of each submap's step (its gate, join and held closures), ms.
        final: the final map in the first pose's frame.
        plain_final: the ungated run's final map (closures held as in the gated run), in the same frame.
        released: the held closures each submap's step joined, with the gate's decision and the
            variance factor it was tested with.
        unheld_final: the ungated run's final map without holding closures (the paper's order).
    """

    states: list[JoinerState]
    variances: list[VarianceFactor]
    results: list[GateResult]
    gate_ms: npt.NDArray[np.float64]
    final: LocalMap
    plain_final: LocalMap
    released: list[tuple[tuple[HeldClosure, GateResult, VarianceFactor], ...]]
    unheld_final: LocalMap

    @property
    def closure_results(self) -> list[tuple[int, HeldClosure, GateResult, VarianceFactor]]:
        """Every held closure's test: ``(index of the submap that reached it, closure, decision, variance factor)``."""
        return [(k, c, r, v) for k, step in enumerate(self.released) for c, r, v in step]

    @property
    def nis(self) -> npt.NDArray[np.float64]:
        """NIS of each submap (0 where nothing was in common)."""
        return np.array([r.nis for r in self.results])

    @property
    def dof(self) -> npt.NDArray[np.int64]:
        """Common scalars of each submap."""
        return np.array([r.dof for r in self.results], dtype=np.int64)

    @property
    def reinitialisations(self) -> list[Reinitialisation]:
        """The features the gate re-initialised on the way (:mod:`~linear_slam_ros.joining.reinit`)."""
        return [Reinitialisation(k + 1, "", front, landmark, self.states[k].n_joined + 1)
                for k, r in enumerate(self.results) for front, landmark in r.reinitialised]

    @property
    def joined_at(self) -> list[int | None]:
        """Each submap's place in the join order (``None``: nothing of it was joined)."""
        return [s.n_joined + 1 if r.submap is not None else None for s, r in zip(self.states, self.results, strict=True)]

    @property
    def gated(self) -> list[int]:
        """Indices of the submaps the gate touched (split something off, gated whole, or a held closure of theirs gated)."""
        own = {k for k, r in enumerate(self.results) if not r.passed}
        return sorted(own | {c.seq - 1 for _, c, r, _ in self.closure_results if not r.passed})

    def fails_at(self, probability: float) -> npt.NDArray[np.bool_]:
        """Which tests (submaps, then held closures) would fail at ``probability`` (evaluated on the recorded NIS, not applied).

        Uses each submap's total NIS and its worst variables (:attr:`GateResult.worst`) with the
        variance factor of that point of the stream; at the probability the stream ran at, these
        are the submaps gated plus those whose failing features were re-initialised instead.
        """
        out = []
        tests = [*zip(self.results, self.variances, strict=True), *((r, v) for _, _, r, v in self.closure_results)]
        for r, v in tests:
            if r.dof == 0:
                out.append(False)
                continue
            p_var = probability ** (1.0 / r.n_common)
            out.append(r.nis > v.threshold(probability, r.dof)
                       or any(w.nis > v.threshold(p_var, w.dof) for w in r.worst))
        return np.array(out, dtype=bool)


def clean_pass(maps: Sequence[LocalMap], probability: float = PROBABILITY, floor: float = 0.0, hold: bool = True) -> CleanPass:
    """Join ``maps`` by online D&C with the gate applied before each submap, and without it.

    ``floor``: lower bound of the variance factor (:class:`VarianceFactor`; 1: a gate that never
    tightens). ``hold``: forward loop closures held back (:mod:`~linear_slam_ros.joining.hold`), in
    the gated and the ungated run.
    """
    state = replace(new_state(JoinMethod.ONLINE_DC), hold_closures=hold, variance=VarianceFactor(floor=floor))
    plain = replace(state, variance=VarianceFactor())
    unheld = replace(plain, hold_closures=False)
    states, variances, results, ms, released = [], [], [], [], []
    for seq, m in enumerate(maps, start=1):
        states.append(state)
        variances.append(state.variance)
        t0 = time.perf_counter()
        step = submap_step(state, m, seq, "", probability)
        ms.append((time.perf_counter() - t0) * 1e3)
        results.append(step.result if step.result is not None else _untested(probability, state.variance))
        released.append(_closure_tests(step, state.variance))
        state = step.state
        plain = submap_step(plain, m, seq).state
        unheld = submap_step(unheld, m, seq).state
        if seq % 250 == 0:
            logger.info("gating: clean pass %d/%d, step ms p50 %.1f, %d gated", seq, len(maps),
                        float(np.median(ms)), sum(not r.passed for r in results))
    return CleanPass(states, variances, results, np.array(ms), _in_first_frame(state), _in_first_frame(plain), released,
                     _in_first_frame(unheld))


def _untested(probability: float, variance: VarianceFactor) -> GateResult:
    """The decision on a submap with nothing left to test (all of it held)."""
    return GateResult(probability, 0.0, 0, float("inf"), variance_factor=variance.value)


def _closure_tests(step: SubmapStep, before: VarianceFactor) -> tuple[tuple[HeldClosure, GateResult, VarianceFactor], ...]:
    """The held closures of a gated step, each with its decision and the variance factor it was tested with.

    That factor is the one before the step, updated by what the step's submap and the closures
    before it let through (as :func:`~linear_slam_ros.joiner.joiner.submap_step` does).
    """
    variance = before.updated(step.result) if step.result is not None and step.result.submap is not None else before
    out = []
    for closure, decision in step.released:
        assert decision is not None  # the step ran with the gate
        out.append((closure, decision, variance))
        if decision.submap is not None:
            variance = variance.updated(decision)
    return tuple(out)


def _in_first_frame(state: JoinerState) -> LocalMap:
    result = global_result(state)
    assert result is not None and state.first_pose_id is not None
    return change_frame(result, state.first_pose_id) if result.frame_id != state.first_pose_id else result


def run_rest(state: JoinerState, maps: Sequence[LocalMap], start: int) -> LocalMap:
    """Join the clean ``maps[start:]`` onto ``state`` as they are, return the final map in the first frame.

    The rest of a trial's stream is clean and joined without the gate (what the gate does to clean
    submaps is the clean check's figure; closures are held as ``state`` says), so the two streams
    differ by submap ``start - 1`` alone.
    A submap that cannot be joined is skipped, as the node rejects it.
    """
    for k in range(start, len(maps)):
        try:
            state = submap_step(state, maps[k], k + 1).state
        except LinearSlamError as exc:
            logger.warning("gating: %s not joined: %s", maps[k].name, exc)
    return _in_first_frame(state)


def position_rms(a: LocalMap, b: LocalMap) -> float:
    """RMS over the variables both maps hold of the position error (m), poses and features alike."""
    lookup = b.key_set
    errs = []
    d = a.dim
    for i, key in enumerate(a.keys.tolist()):
        j = lookup.get(key)
        if j is not None:
            errs.append(a.x[a.scalar_slice(i)][:d] - b.x[b.scalar_slice(j)][:d])
    return float(np.sqrt(np.mean(np.sum(np.square(errs), axis=1)))) if errs else 0.0


def corrupt(submap: LocalMap, var_index: int, rng: np.random.Generator) -> LocalMap:
    """Move one variable of ``submap`` (corruption model of the module docstring)."""
    x = submap.x.copy()
    sl = submap.scalar_slice(var_index)
    d = submap.dim
    direction = rng.normal(size=d)
    direction /= np.linalg.norm(direction)
    if submap.kinds[var_index] == POSE:
        x[sl.start:sl.start + d] += rng.uniform(1.0, 3.0) * direction
        x[sl.start + d] += np.deg2rad(rng.uniform(15.0, 45.0)) * rng.choice([-1.0, 1.0])
    else:
        x[sl.start:sl.start + d] += rng.uniform(2.0, 5.0) * direction
    return submap.replace(x=x)


def closures_tested(clean: CleanPass) -> dict[int, dict[int, int]]:
    """Held closures the gate tested in the clean pass: submap index -> {target pose id: index of the submap that reached it}."""
    out: dict[int, dict[int, int]] = {}
    for j, closure, result, _ in clean.closure_results:
        if result.dof > 0:
            out.setdefault(closure.seq - 1, {})[closure.target] = j
    return out


def corruptible(k: int, maps: Sequence[LocalMap], clean: CleanPass, closures: dict[int, dict[int, int]]) -> list[int]:
    """Indices of the variables of submap ``k`` a trial may move: those the map held before it (but its end
    pose), and the poses of its held closures that the gate tested."""
    targets = closures.get(k, {})
    held = [i for i, (pid, kind) in enumerate(zip(maps[k].ids.tolist(), maps[k].kinds.tolist(), strict=True))
            if kind == POSE and pid in targets]
    common = _common_vars(clean.states[k], maps[k]) if clean.dof[k] > 0 else []
    return sorted(set(common) | set(held))


def any_corruptible(maps: Sequence[LocalMap], clean: CleanPass) -> bool:
    """Whether a submap has a variable to corrupt (:func:`corruptible`)."""
    closures = closures_tested(clean)
    return any(corruptible(k, maps, clean, closures) for k in range(1, len(maps)))


def _common_vars(state: JoinerState, submap: LocalMap) -> list[int]:
    """Variables of ``submap`` the map holds, but its end pose (the chain goes on from it: not a loop closure)."""
    known = global_keys(state)
    end = pose_key(submap.end_id) if submap.end_id is not None else None
    renamed = state.relabels.apply(submap)  # same variables in the same order, re-initialised features renamed
    return [i for i, k in enumerate(renamed.keys.tolist()) if k in known and k != end]


def global_keys(state: JoinerState) -> set[int]:
    """Keys of every variable the state's map holds (from the stack's parts; no merge)."""
    out: set[int] = set()
    for leaf in leaf_maps(state.joined.stack):
        out.update(leaf.key_set)
    return out


def _load(name: str, datasets_dir: Path) -> list[LocalMap]:
    archive = datasets_dir / f"{name}.tar.xz"
    return list(read_dataset(archive if archive.exists() else datasets_dir / name).maps)


def _same(a: LocalMap | None, b: LocalMap | None) -> bool:
    """Whether two submaps are the same bit for bit (variables, estimate, information)."""
    if a is None or b is None:
        return a is b
    info_a, info_b = (m.info.toarray() if sp.issparse(m.info) else m.info for m in (a, b))
    return (a.frame_id == b.frame_id and a.keys.tolist() == b.keys.tolist() and np.array_equal(a.x, b.x)
            and np.array_equal(info_a, info_b))


def _draw(
    rng: np.random.Generator, candidates: Sequence[int], clean: CleanPass, maps: Sequence[LocalMap],
    closures: dict[int, dict[int, int]],
) -> tuple[int, int, LocalMap]:
    """One trial's corruption: submap index ``k``, variable index ``v`` in it, the corrupted submap.

    Submaps of ``candidates`` with nothing to corrupt are drawn again (some must have one: :func:`any_corruptible`).
    """
    while True:
        k = int(rng.choice(candidates))
        common = corruptible(k, maps, clean, closures)
        if common:
            v = int(rng.choice(common))
            return k, v, corrupt(maps[k], v, rng)


@dataclass(frozen=True)
class Trial:
    """One corrupted trial, up to the gate's decision on the moved variable.

    Attributes:
        decision: the gate's decision that tested the moved variable (the submap's, or its held closure's).
        hit: the moved variable was gated.
        got, ref: the corrupted stream's and the reference stream's states right after that decision.
        rest: index of the first submap neither has joined yet.
        released_at: sequence number of the submap whose step tested the held closure (``None``: the submap's own test).
    """

    decision: GateResult
    hit: bool
    got: JoinerState
    ref: JoinerState
    rest: int
    released_at: int | None


def run_trial(
    clean: CleanPass, maps: Sequence[LocalMap], closures: dict[int, dict[int, int]], k: int, v: int, bad: LocalMap,
    probability: float,
) -> Trial:
    """Gate the corrupted submap ``bad`` (variable ``v`` of submap ``k`` moved) and its reference (``v`` marginalised out).

    A moved held closure is decided when the chain reaches its pose: the submaps in between are
    joined without the gate, that one with it (at the clean pass's variance factor there).
    """
    state = clean.states[k]
    got = submap_step(state, bad, k + 1, "", probability)
    ref = submap_step(state, marginalise_out(maps[k], [v]), k + 1, "", probability)
    key = (int(bad.ids[v]), int(bad.kinds[v]))
    j = closures.get(k, {}).get(key[0]) if key[1] == POSE else None
    if j is None:
        assert got.result is not None
        hit = key in {(state.relabels.front_id(g.var_id) if g.kind == FEATURE else g.var_id, g.kind)
                      for g in got.result.split}
        return Trial(got.result, hit, got.state, ref.state, k + 1, None)
    a, b = got.state, ref.state
    for i in range(k + 1, j):
        a, b = submap_step(a, maps[i], i + 1).state, submap_step(b, maps[i], i + 1).state
    variance = clean.variances[j]
    got = submap_step(replace(a, variance=variance), maps[j], j + 1, "", probability)
    ref = submap_step(replace(b, variance=variance), maps[j], j + 1, "", probability)
    decision = next(r for c, r in got.released if c.seq == k + 1 and c.target == key[0])
    assert decision is not None
    return Trial(decision, not decision.passed, got.state, ref.state, j + 1, j + 1)


def _same_state(a: JoinerState, b: JoinerState) -> bool:
    """Whether two online D&C states hold the same maps and held closures bit for bit (what the rest of a stream depends on)."""
    leaves_a, leaves_b = leaf_maps(a.joined.stack), leaf_maps(b.joined.stack)
    return (len(leaves_a) == len(leaves_b) and all(_same(x, y) for x, y in zip(leaves_a, leaves_b, strict=True))
            and [(h.seq, h.target) for h in a.held] == [(h.seq, h.target) for h in b.held]
            and all(_same(x.measured, y.measured) for x, y in zip(a.held, b.held, strict=True)))


def clean_check(name: str, maps: Sequence[LocalMap], clean: CleanPass, seconds: float) -> dict[str, Any]:
    """Figures of the clean stream: submaps gated, χ² gated and ungated, per-probability fractions, gate time."""
    tested = clean.dof > 0
    gated = clean.gated
    chi2_gated = chi2(clean.final, as_joined(maps, clean.reinitialisations, clean.joined_at))  # under the ids joined
    chi2_plain = chi2(clean.plain_final, maps)
    identical = clean.final.keys.tolist() == clean.plain_final.keys.tolist() and bool(
        np.array_equal(clean.final.x, clean.plain_final.x))
    closure_tests = [r for _, _, r, _ in clean.closure_results if r.dof > 0]
    nis = np.concatenate([clean.nis, [r.nis for r in closure_tests]])
    dof = np.concatenate([clean.dof, [r.dof for r in closure_tests]]).astype(np.int64)
    ratio = nis[dof > 0] / dof[dof > 0]
    testing = tested | np.array([any(r.dof > 0 for _, r, _ in step) for step in clean.released], dtype=bool)
    return {
        "dataset": name, "n_submaps": len(maps), "n_tested": int(tested.sum()),
        "n_closures_tested": len(closure_tests),
        "clean_gated": len(gated), "clean_gated_fraction": len(gated) / len(maps),
        "clean_reinitialised": [r.as_dict() for r in clean.reinitialisations],
        "clean_gated_decisions": [
            {"submap": k + 1, "nis": clean.results[k].nis, "dof": clean.results[k].dof,
             "threshold": clean.results[k].threshold, "variance_factor": clean.results[k].variance_factor,
             "split": [[g.var_id, g.kind] for g in clean.results[k].split], "rejected": clean.results[k].rejected}
            for k in gated if not clean.results[k].passed],
        "clean_gated_closures": [
            {"submap": c.seq, "closure": [c.origin, c.target], "tested_at": j + 1, "nis": r.nis, "dof": r.dof,
             "threshold": r.threshold, "variance_factor": r.variance_factor}
            for j, c, r, _ in clean.closure_results if not r.passed],
        "chi2_gated": chi2_gated, "chi2_plain": chi2_plain, "map_identical_to_ungated": identical,
        "chi2_unheld": chi2(clean.unheld_final, maps),
        "clean_fails_at": {f"{p}": int(clean.fails_at(p).sum()) for p in PROBABILITIES},
        "variance_factor_final": clean.variances[-1].updated(clean.results[-1]).value,
        "clean_nis_sum": float(nis.sum()), "clean_dof_sum": int(dof.sum()),
        "clean_nis_over_dof_median": float(np.median(ratio)) if ratio.size else 0.0,
        "clean_nis_over_dof_max": float(np.max(ratio)) if ratio.size else 0.0,
        # steps that tested something (the submap, or a held closure): gate, join and released closures
        "gate_ms_p50": float(np.median(clean.gate_ms[testing])) if testing.any() else 0.0,
        "gate_ms_p99": float(np.percentile(clean.gate_ms[testing], 99)) if testing.any() else 0.0,
        "gate_ms_max": float(np.max(clean.gate_ms)), "clean_pass_seconds": seconds,
    }


def run_dataset(
    name: str, datasets_dir: Path, trials: int, seed: int, probability: float, verify: int = 1, floor: float = 0.0,
    hold: bool = True,
) -> dict[str, Any]:
    """Clean pass, then ``trials`` corrupted trials (none: the clean check alone), on one dataset; returns its figures.

    A trial whose two states are the same bit for bit once the moved variable is decided on has
    error 0 without re-running (the rest of both streams is the same); ``verify`` of them (the
    latest in the stream: the cheapest) are re-run anyway to prove it, and every other trial is
    re-run to the end.
    """
    maps = _load(name, datasets_dir)
    t0 = time.perf_counter()
    clean = clean_pass(maps, probability, floor, hold)
    out = clean_check(name, maps, clean, time.perf_counter() - t0)
    out.update({"probability": probability, "trials": trials, "variance_floor": floor, "hold_closures": hold})
    if not trials:
        return out
    closures = closures_tested(clean)
    candidates = [k for k in range(1, len(maps)) if clean.dof[k] > 0 or k in closures]
    if not any_corruptible(maps, clean):  # sphere2500 without holding: every variable it shares is an end pose
        why = "no submap shares a variable other than its end pose with the map, and no held closure was tested"
        logger.warning("gating: %s: %s; no corruption trial can be drawn (clean check only)", name, why)
        out.update({"trials": 0, "trials_skipped": why})
        return out
    detected, errors = 0, []
    rows: list[dict[str, Any]] = []
    t0 = time.perf_counter()
    for t in range(trials):
        k, v, bad = _draw(np.random.default_rng(seed + t), candidates, clean, maps, closures)
        trial = run_trial(clean, maps, closures, k, v, bad, probability)
        key = (int(bad.ids[v]), int(bad.kinds[v]))
        detected += trial.hit
        exact = _same_state(trial.got, trial.ref)
        error = 0.0 if exact else position_rms(run_rest(trial.got, maps, trial.rest), run_rest(trial.ref, maps, trial.rest))
        errors.append(error)
        r = trial.decision
        rows.append({"trial": t, "submap": k + 1, "variable": list(key), "detected": bool(trial.hit),
                     "held_closure_tested_at": trial.released_at, "nis": r.nis, "dof": r.dof, "threshold": r.threshold,
                     "variable_nis": next((w.nis for w in r.worst if (w.var_id, w.kind) == key), None)
                     if trial.released_at is None else r.nis,
                     "variable_threshold": r.variable_threshold, "variance_factor": r.variance_factor,
                     "split": [[g.var_id, g.kind] for g in r.split], "rejected": r.rejected,
                     "rms_m": error, "rerun": not exact})
        if (t + 1) % 10 == 0:
            logger.info("gating: %s trial %d/%d, detected %d, max rms %.4f m", name, t + 1, trials, detected,
                        max(errors))
    exact_rows = sorted((r for r in rows if not r["rerun"]), key=lambda r: -int(r["submap"]))
    for row in exact_rows[:verify]:  # the proof that an exact split costs nothing: re-run anyway
        index = int(row["trial"])
        k, v, bad = _draw(np.random.default_rng(seed + index), candidates, clean, maps, closures)
        trial = run_trial(clean, maps, closures, k, v, bad, probability)
        row["rms_m"] = position_rms(run_rest(trial.got, maps, trial.rest), run_rest(trial.ref, maps, trial.rest))
        row["rerun"] = True
        errors[index] = float(row["rms_m"])
    out.update({
        "detected": detected, "detection_rate": detected / trials,
        "rms_max_m": max(errors), "rms_mean_m": float(np.mean(errors)),
        "rms_over_0_05": int(sum(e > 0.05 for e in errors)), "trials_seconds": time.perf_counter() - t0,
        "held_closure_trials": sum(r["held_closure_tested_at"] is not None for r in rows),
        "misses": [r for r in rows if not r["detected"]], "rows": rows,
    })
    return out


def write_outputs(results: list[dict[str, Any]], out: Path, command: str) -> None:
    """Write ``gating.json`` and ``gating.md`` into ``out`` (acceptance: issue 11, part 3)."""
    out.mkdir(parents=True, exist_ok=True)
    (out / "gating.json").write_text(json.dumps(results, indent=1))
    trials = [r for r in results if r["trials"]]
    lines = [
        "# χ² gating benchmark", "", f"`{command}`", "",
        f"Gate probability {results[0]['probability'] if results else PROBABILITY}, the stream's variance factor "
        f"carried along (`joining/gate.py`; floor {results[0].get('variance_floor', 0.0) if results else 0.0}). "
        "Acceptance: detected ≥ 95%, max RMS ≤ 0.05 m, clean gated ≤ 0.5%.", "",
        "## Corrupted measurement (one per trial)", "",
        "| dataset | submaps (tested) | trials | of them held closures | detected | missed | max RMS vs clean-without-it, m "
        "| trials > 0.05 m | trial time, s |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in trials:
        lines.append(
            f"| {r['dataset']} | {r['n_submaps']} ({r['n_tested']}) | {r['trials']} | {r.get('held_closure_trials', 0)} | "
            f"{100 * r['detection_rate']:.0f}% | {r['trials'] - r['detected']} | {r['rms_max_m']:.4f} | "
            f"{r['rms_over_0_05']} | {r['trials_seconds']:.0f} |"
        )
    lines += [
        "", "## Clean data", "",
        "Closures are held as in the gated run in the ungated one (`hold_closures`); the last χ² is the ungated run's "
        "without holding (the paper's order).", "",
        "| dataset | submaps (tested) | held closures tested | gated | features re-initialised "
        "| χ² gated / ungated / ungated, not held | map = ungated | final variance factor "
        "| Σ NIS / Σ dof | median, max NIS/dof | would gate at " + " / ".join(f"{p}" for p in PROBABILITIES)
        + " | step ms (gate, join, closures) p50 / p99 / max |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in results:
        fails = " / ".join(f"{r['clean_fails_at'][f'{p}']}" for p in PROBABILITIES)
        lines.append(
            f"| {r['dataset']} | {r['n_submaps']} ({r['n_tested']}) | {r.get('n_closures_tested', 0)} | {r['clean_gated']} "
            f"({100 * r['clean_gated_fraction']:.2f}%) | {len(r.get('clean_reinitialised', []))} | "
            f"{r['chi2_gated']:.2f} / {r['chi2_plain']:.2f} / {r.get('chi2_unheld', r['chi2_plain']):.2f} | "
            f"{'yes' if r['map_identical_to_ungated'] else 'no'} | {r['variance_factor_final']:.2f} | "
            f"{r['clean_nis_sum']:.0f} / {r['clean_dof_sum']} | {r['clean_nis_over_dof_median']:.2f}, "
            f"{r['clean_nis_over_dof_max']:.1f} | {fails} | "
            f"{r['gate_ms_p50']:.1f} / {r['gate_ms_p99']:.1f} / {r['gate_ms_max']:.1f} |"
        )
    misses = [(r["dataset"], m) for r in trials for m in r["misses"]]
    if misses:
        lines += ["", "## Missed corruptions", "",
                  "| dataset | trial | submap | variable (id, kind) | its conditional NIS | threshold | submap NIS / threshold "
                  "| RMS, m |", "|---|---|---|---|---|---|---|---|"]
        for name, m in misses:
            vnis = "–" if m["variable_nis"] is None else f"{m['variable_nis']:.1f}"
            lines.append(f"| {name} | {m['trial']} | {m['submap']} | {m['variable']} | {vnis} | "
                         f"{m['variable_threshold']:.1f} | {m['nis']:.1f} / {m['threshold']:.1f} | {m['rms_m']:.4f} |")
    (out / "gating.md").write_text("\n".join(lines) + "\n")


def main(argv: Sequence[str] | None = None) -> int:
    """Command line: see the module docstring."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--datasets-dir", type=Path, default=Path("../shared/datasets"))
    parser.add_argument("--out", type=Path, default=Path("out/benchmark"))
    parser.add_argument("--only", nargs="*", default=list(DATASETS))
    parser.add_argument("--clean-only", nargs="*", default=list(CLEAN_ONLY))
    parser.add_argument("--trials", type=int, default=100)
    parser.add_argument("--seed", type=int, default=11)
    parser.add_argument("--probability", type=float, default=PROBABILITY)
    parser.add_argument("--variance-floor", type=float, default=0.0,
                        help="lower bound of the stream's variance factor (1: the gate never tightens)")
    parser.add_argument("--no-hold", action="store_true",
                        help="fuse forward loop closures on arrival, untested (the joiner's order without the gate)")
    parser.add_argument("--merge", nargs="+", type=Path, default=None,
                        help="only merge these gating.json files (runs split over processes) into --out")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    given = argv if argv is not None else sys.argv[1:]
    command = "python -m linear_slam_ros.evaluation.gating " + " ".join(given)
    results = []
    if args.merge:
        for path in args.merge:
            results.extend(json.loads(path.read_text()))
        write_outputs(results, args.out, command)
        return 0
    jobs = [(name, args.trials) for name in args.only] + [(name, 0) for name in args.clean_only]
    for name, trials in jobs:
        if not any((args.datasets_dir / n).exists() for n in (f"{name}.tar.xz", name)):
            logger.warning("gating: no %s in %s, skipped", name, args.datasets_dir)
            continue
        r = run_dataset(name, args.datasets_dir, trials, args.seed, args.probability, floor=args.variance_floor,
                        hold=not args.no_hold)
        logger.info("%s: detected %s/%d, max rms %s m, clean gated %d/%d, χ² %.2f (ungated %.2f)", name,
                    r.get("detected", "-"), trials, r.get("rms_max_m", "-"), r["clean_gated"], r["n_submaps"],
                    r["chi2_gated"], r["chi2_plain"])
        results.append(r)
        write_outputs(results, args.out, command)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
