"""RMSE and latency summaries on hand-computed cases."""

from __future__ import annotations

import numpy as np
import pytest

from linear_slam_ros.core.errors import FrameError, InvalidMapError
from linear_slam_ros.core.local_map import FEATURE, POSE, LocalMap
from linear_slam_ros.core.timing import latency_summary
from linear_slam_ros.evaluation.metrics import nees, rmse


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


def test_nees_is_tested_one_sided_at_its_confidence_as_in_the_paper():
    """Table 3 of the paper: the 95% bound for 1224 scalars is 1306.5 (one-sided). A map of 6 pose
    scalars with an error whose NEES is 13.5 is above the 95% bound 12.59 (it was called consistent
    against the two-sided 97.5% quantile, 14.45)."""
    from scipy.stats import chi2

    assert round(float(chi2.ppf(0.95, 1224)), 1) == 1306.5
    m = LocalMap(2, 0, 2, np.array([1, 2]), np.array([POSE, POSE], dtype=np.int8), np.zeros(6), np.eye(6), "m")
    truth = {(POSE, 1): np.zeros(3), (POSE, 2): np.zeros(3)}
    truth[(POSE, 2)][0] = -np.sqrt(13.5)  # NEES = 13.5 with identity information
    result = nees(m, truth)
    assert result.nees == pytest.approx(13.5) and result.dof == 6
    assert result.bound == pytest.approx(12.5916, abs=1e-4) and not result.consistent
    assert (result.lower, result.upper) == pytest.approx((1.2373, 14.4494), abs=1e-4)
    assert nees(m, truth, confidence=0.99).consistent  # 16.81 at 99%
