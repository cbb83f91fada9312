"""Test support shared by the suites: where the benchmark datasets are, reference joiners."""

from __future__ import annotations

import os
from collections.abc import Iterable
from pathlib import Path

import pytest

from linear_slam_ros.core.errors import InvalidMapError
from linear_slam_ros.core.local_map import LocalMap
from linear_slam_ros.joining.divide_conquer import OnlineDCState, online_dc_result, online_dc_step
from linear_slam_ros.joining.pairwise import join_pair, to_end_frame
from linear_slam_ros.joining.sequential import SequentialState, sequential_step

REPO = Path(__file__).resolve().parents[1]
DATASETS = Path(os.environ.get("LINEAR_SLAM_DATASETS", REPO.parent / "shared" / "datasets"))
CACHE = REPO / ".cache" / "datasets"


def dataset_archive(name: str) -> Path:
    """Return the archive of a benchmark dataset; fail (not skip) when ../shared is missing."""
    path = DATASETS / f"{name}.tar.xz"
    if not path.exists():
        pytest.fail(f"benchmark dataset {path} is missing: ../shared must sit beside the repository")
    return path


def join_sequential_information(maps: Iterable[LocalMap]) -> LocalMap:
    """Join maps one at a time with the paper's information-form step (Sec. 5.1), in end-pose frames.

    The literal recursion of the paper, kept as the reference that
    :mod:`linear_slam_ros.joining.sequential` (covariance form) must equal.
    """
    it = iter(maps)
    try:
        result = to_end_frame(next(it))
    except StopIteration:
        raise InvalidMapError("no local maps to join") from None
    for local_map in it:
        result = join_pair(result, local_map)
    return result


def join_online_dc(maps: Iterable[LocalMap]) -> LocalMap:
    """Join maps with the online divide-and-conquer stack and return the merged result."""
    state = OnlineDCState()
    for m in maps:
        state = online_dc_step(state, m)
    return online_dc_result(state)


def join_sequential(maps: Iterable[LocalMap]) -> LocalMap:
    """Join maps exactly and sequentially; return the global map in the last end pose's frame."""
    state = SequentialState()
    for m in maps:
        state = sequential_step(state, m)
    if state.global_map is None:
        raise InvalidMapError("no local maps to join")
    return state.global_map.to_local_map()
