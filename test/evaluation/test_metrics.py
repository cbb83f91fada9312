"""RMSE and latency summaries on hand-computed cases."""

from __future__ import annotations

import numpy as np
import pytest

from linear_slam_ros.core.errors import FrameError, InvalidMapError
from linear_slam_ros.core.local_map import FEATURE, POSE, LocalMap
from linear_slam_ros.core.timing import latency_summary
from linear_slam_ros.evaluation.metrics import rmse


def _m(x, frame=0, name="m"):
    ids, kinds = np.array([1, 5]), np.array([POSE, FEATURE], np.int8)
    return LocalMap(2, frame, None, ids, kinds, np.asarray(x, float), np.eye(5), name=name)


def test_rmse_per_coordinate_known_values():
    a = _m([0, 0, 0, 1, 1])
    b = _m([3, 4, 2, 1, 2])
    assert rmse(a, b, POSE) == pytest.approx(np.sqrt(25 / 2))
    assert rmse(a, b, FEATURE) == pytest.approx(np.sqrt(1 / 2))


def test_rmse_errors():
    with pytest.raises(FrameError, match="'a' is in pose 0, 'b' in pose 9"):
        rmse(_m([0] * 5, name="a"), _m([0] * 5, frame=9, name="b"), POSE)
    c = LocalMap(2, 0, None, np.array([8]), np.array([FEATURE], np.int8), np.zeros(2), np.eye(2), name="c")
    with pytest.raises(InvalidMapError, match="share no feature"):
        rmse(_m([0] * 5), c, FEATURE)


def test_latency_summary_in_milliseconds():
    s = latency_summary([0.001] * 99 + [0.5])
    assert s["per_submap_ms_p50"] == pytest.approx(1.0)
    assert s["per_submap_ms_max"] == pytest.approx(500.0)
    assert latency_summary([])["per_submap_ms_max"] == 0.0
