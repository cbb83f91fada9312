"""Input limits: the value, and the numeric checks of LocalMap validation (magnitudes, conditioning,
angles, coordinates), each with an error naming the limit and the value; sparse checks never densify."""

from __future__ import annotations

import dataclasses
import re
import resource
import time

import numpy as np
import pytest
import scipy.linalg
import scipy.sparse as sp

from linear_slam_ros.core import local_map as local_map_module
from linear_slam_ros.core.errors import ConfigError, InvalidMapError
from linear_slam_ros.core.limits import DEFAULT_LIMITS, LIMIT_NAMES, NODE_LIMITS, InputLimits
from linear_slam_ros.core.local_map import (
    FEATURE,
    POSE,
    LocalMap,
    check_block_diagonal_information,
    check_information,
)
from linear_slam_ros.joiner.config import JoinerConfig


def _map(x=None, info=None, limits=None, **over):
    kw = dict(
        dim=2,
        frame_id=0,
        end_id=1,
        ids=np.array([1, 7]),
        kinds=np.array([POSE, FEATURE], dtype=np.int8),
        x=np.array([1.0, 0.0, 0.1, 2.0, 3.0]) if x is None else np.asarray(x, dtype=float),
        info=np.eye(5) * 10 if info is None else info,
        name="lm",
    )
    kw.update(over)
    m = LocalMap.trusted(**kw)
    m.validate(limits)
    return m


def test_defaults_sit_far_outside_the_benchmarks():
    d = InputLimits()
    assert d == DEFAULT_LIMITS
    # measured maxima (README, "Input limits"): local maps 75 scalars, 2,850 triplets, 44 edges a chunk,
    # information diagonal in [0.58, 1.7e6], condition 6e5 (global maps 1.8e11), |angle| <= pi, 254 m
    assert d.max_state_scalars >= 4 * 21_292 and d.max_info_triplets >= 4 * 4_000_000 and d.max_chunk_edges >= 200 * 44
    assert d.min_information <= 1e-11 * 0.58 and d.max_information >= 1e5 * 1.7e6
    assert d.max_condition >= 100 * 1.8e11 and d.max_angle >= 1000 * np.pi and d.max_coordinate >= 1000 * 254
    assert NODE_LIMITS.max_state_scalars >= 50 * 75 and NODE_LIMITS.max_info_triplets >= 500 * 2_850
    assert dataclasses.replace(NODE_LIMITS, max_state_scalars=d.max_state_scalars, max_info_triplets=d.max_info_triplets) == d


def test_node_parameters_are_the_limits_with_the_same_names():
    config = JoinerConfig()
    assert set(LIMIT_NAMES) <= {f.name for f in dataclasses.fields(JoinerConfig)}
    assert InputLimits(**{name: getattr(config, name) for name in LIMIT_NAMES}) == NODE_LIMITS
    changed = JoinerConfig.from_mapping({"max_angle": 7.0, "max_state_scalars": 12})
    assert (changed.max_angle, changed.max_state_scalars) == (7.0, 12)


@pytest.mark.parametrize(
    "over, match",
    [
        (dict(max_state_scalars=0), "input limit max_state_scalars=0 must be an integer >= 1"),
        (dict(max_chunk_edges=2.5), "input limit max_chunk_edges=2.5 must be an integer >= 1"),
        (dict(max_angle=float("inf")), "input limit max_angle=inf must be a finite number > 0"),
        (dict(min_information=-1.0), "input limit min_information=-1.0 must be a finite number > 0"),
        (dict(min_information=10.0, max_information=1.0), "min_information=10 is above max_information=1"),
        (dict(max_condition=0.5), "input limit max_condition=0.5 must be >= 1"),
    ],
)
def test_limits_are_checked(over, match):
    with pytest.raises(ConfigError, match=match):
        InputLimits(**over)


@pytest.mark.parametrize(
    "x, info, match",
    [
        (None, np.diag([10.0, 10, 1e-300, 10, 10]),
         "information diagonal entry 2 \\(pose 1\\) is 1e-300, below the limit min_information = 1e-12"),
        (None, np.diag([10.0, 10, 10, 1e300, 10]),
         "information diagonal entry 3 \\(feature 7\\) is 1e\\+300, above the limit max_information = 1e\\+12"),
        (None, np.diag([1e10, 1e10, 1e10, 1e-6, 1e-6]),
         "information matrix is too ill-conditioned to join in double precision: condition number 1e\\+16 "
         "\\(1-norm estimate\\) is above the limit "
         "max_condition = 1e\\+14"),
        ([1.0, 0.0, 1e300, 2.0, 3.0], None,
         "angle at state index 2 \\(pose 1\\) is 1e\\+300 rad, beyond the limit max_angle = 10000 rad"),
        ([1.0, 0.0, -1e5, 2.0, 3.0], None, "angle at state index 2 \\(pose 1\\) is -1e\\+05 rad, beyond the limit max_angle"),
        ([1.0, 0.0, 0.1, 2.0, -1e300], None,
         "coordinate at state index 4 \\(feature 7\\) is -1e\\+300 m, beyond the limit max_coordinate = 1e\\+06 m"),
        ([1e7, 0.0, 0.1, 2.0, 3.0], None,
         "coordinate at state index 0 \\(pose 1\\) is 1e\\+07 m, beyond the limit max_coordinate"),
    ],
)
def test_numbers_beyond_the_default_limits_are_rejected(x, info, match):
    with pytest.raises(InvalidMapError, match=f"^local map 'lm': {match}"):
        _map(x, info)
    with pytest.raises(InvalidMapError, match=match):  # construction validates with the default limits too
        LocalMap(2, 0, 1, np.array([1, 7]), np.array([POSE, FEATURE], np.int8), _map().x if x is None else np.array(x),
                 np.eye(5) * 10 if info is None else info, name="lm")


def test_a_non_positive_diagonal_is_not_positive_definite_before_any_bound():
    with pytest.raises(InvalidMapError, match="^local map 'lm': information matrix is not positive definite$"):
        _map(info=np.diag([10.0, 10, 10, 10, 0.0]))


def test_custom_limits_apply_and_the_defaults_accept_what_they_refuse():
    limits = InputLimits(max_angle=4.0, max_coordinate=10.0, min_information=1.0, max_information=100.0, max_condition=50.0)
    _map([1.0, 0.0, 5.0, 2.0, 3.0])  # 5 rad: fine by default
    with pytest.raises(InvalidMapError, match="angle at state index 2 \\(pose 1\\) is 5 rad, beyond the limit max_angle = 4 rad"):
        _map([1.0, 0.0, 5.0, 2.0, 3.0], limits=limits)
    match = "coordinate at state index 3 \\(feature 7\\) is 20 m, beyond the limit max_coordinate = 10 m"
    with pytest.raises(InvalidMapError, match=match):
        _map([1.0, 0.0, 0.1, 20.0, 3.0], limits=limits)
    with pytest.raises(InvalidMapError, match="entry 0 \\(pose 1\\) is 0.5, below the limit min_information = 1$"):
        _map(info=np.diag([0.5, 10, 10, 10, 10]), limits=limits)
    with pytest.raises(InvalidMapError, match="entry 4 \\(feature 7\\) is 200, above the limit max_information = 100$"):
        _map(info=np.diag([10.0, 10, 10, 10, 200]), limits=limits)
    with pytest.raises(InvalidMapError, match="condition number 90 \\(1-norm estimate\\) is above the limit max_condition = 50$"):
        _map(info=np.diag([1.0, 90, 10, 10, 10]), limits=limits)
    _map(info=np.diag([2.0, 90, 10, 10, 10]), limits=limits)  # condition 45


def test_condition_estimate_is_that_of_the_matrix_dense_and_sparse(monkeypatch, rng):
    n = 60
    q, _ = np.linalg.qr(rng.normal(size=(n, n)))
    info = q @ np.diag(np.logspace(-2, 6, n)) @ q.T
    info = 0.5 * (info + info.T)
    exact = np.abs(info).sum(0).max() * np.abs(np.linalg.inv(info)).sum(0).max()
    assert 1e8 < exact < 1e11
    below, above = InputLimits(max_condition=exact / 3.5), InputLimits(max_condition=exact * 1.01)
    for matrix in (info, sp.csr_matrix(info)):
        monkeypatch.setattr(local_map_module, "_DENSE_CHECK_MAX", 10)  # sparse: the LU path
        check_information(matrix, "m", above)
        with pytest.raises(InvalidMapError, match="^m: information matrix is too ill-conditioned"):
            check_information(matrix, "m", below)
        monkeypatch.undo()


def test_block_diagonal_check_is_the_exact_one_norm_condition_of_the_whole_matrix(rng):
    """Blocks each well conditioned, the whole matrix not: the condition is the dense matrix's 1-norm one."""
    blocks = []
    for scale in (1e-3, 1.0, 1e5):
        a = rng.normal(size=(3, 3))
        blocks.append(scale * (a @ a.T + 3 * np.eye(3)))
    blocks = np.stack(blocks)
    dense = scipy.linalg.block_diag(*blocks)
    exact = float(np.linalg.cond(dense, 1))
    assert max(np.linalg.cond(b, 1) for b in blocks) < 1e3 < 1e7 < exact
    check_block_diagonal_information(blocks, "m", InputLimits(max_condition=exact * (1 + 1e-9)))
    check_information(dense, "m", InputLimits(max_condition=exact * (1 + 1e-9)))  # the estimate is at most the exact value
    below = InputLimits(max_condition=exact * (1 - 1e-9))
    match = f"^m: .* condition number {re.escape(f'{exact:.3g}')} \\(1-norm\\) is above the limit"
    with pytest.raises(InvalidMapError, match=match):
        check_block_diagonal_information(blocks, "m", below)
    check_block_diagonal_information(blocks[:0], "m", below)  # no variable: nothing to check


def test_block_diagonal_check_names_the_entry_and_a_singular_block():
    blocks = np.stack([np.eye(3), np.diag([1.0, 1e-13, 1.0])])
    describe = {i: f"pose {i // 3}" for i in range(6)}.get
    with pytest.raises(InvalidMapError, match="^m: information diagonal entry 4 \\(pose 1\\) is 1e-13, below the limit min"):
        check_block_diagonal_information(blocks, "m", None, describe)
    singular = np.stack([np.eye(2), np.ones((2, 2))])
    with pytest.raises(InvalidMapError, match="^m: information matrix is singular$"):
        check_block_diagonal_information(singular, "m")


def test_check_numbers_is_validate_without_the_structure():
    m = _map()
    m.check_numbers()
    bad = _map().replace(x=np.array([1.0, 0.0, np.nan, 2.0, 3.0]))
    with pytest.raises(InvalidMapError, match="^local map 'lm': state entry 2 is not finite \\(nan\\)$"):
        bad.check_numbers()


def test_large_sparse_information_is_checked_without_densifying():
    """200,000 scalars (a dense copy: 320 GB) with a bad entry at the end: found by the sparse path, in bounded memory."""
    n = 200_000
    diag = np.full(n, 100.0)
    ids = np.arange(1, n // 2 + 1)
    kinds = np.full(n // 2, FEATURE, np.int8)
    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    t0 = time.perf_counter()
    LocalMap(2, 0, None, ids, kinds, np.zeros(n), sp.diags(diag).tocsr(), name="big")  # valid: accepted
    diag[-1] = 1e-20
    match = "'big': information diagonal entry 199999 \\(feature 100000\\) is 1e-20, below the limit min_information"
    with pytest.raises(InvalidMapError, match=match):
        LocalMap(2, 0, None, ids, kinds, np.zeros(n), sp.diags(diag).tocsr(), name="big")
    diag[0], diag[-1] = 1e12, 1e-3  # within the bounds, but the matrix is too ill-conditioned
    match = "'big': .* condition number 1e\\+15 \\(1-norm estimate\\) is above the limit max_condition"
    with pytest.raises(InvalidMapError, match=match):
        LocalMap(2, 0, None, ids, kinds, np.zeros(n), sp.diags(diag).tocsr(), name="big")
    assert time.perf_counter() - t0 < 10.0
    assert (resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - before) / 1024 < 200  # ru_maxrss is in KiB
