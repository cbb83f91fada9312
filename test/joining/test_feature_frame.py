"""Pose-feature maps moved to a frame defined by their features and back (``joining/feature_frame.py``)."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp

from linear_slam_ros.core.local_map import FEATURE, POSE, LocalMap, to_dense
from linear_slam_ros.core.solvers import DENSE_MAX
from linear_slam_ros.joining.feature_frame import from_feature_frame, to_feature_frame


@pytest.mark.parametrize("n_features", [20, 70])  # 46 and 146 scalars: the dense path and the sparse one
def test_to_a_feature_frame_and_back_is_exact_on_either_side_of_dense_max(n_features, rng):
    """The sparse path (above DENSE_MAX scalars) was never run by a test: its symmetrisation could be off by a
    factor of 2 unseen (mutation audit, session 26)."""
    kinds = np.array([POSE, POSE] + [FEATURE] * n_features, np.int8)
    ids = np.r_[1, 2, 10 + np.arange(n_features)]
    x = np.r_[1.0, 0.5, 0.2, 2.0, 1.0, -0.3, rng.normal(size=2 * n_features) * 5]
    a = rng.normal(size=(x.size, x.size)) * 0.1
    info = sp.csr_matrix(np.eye(x.size) * 10 + 0.5 * (a + a.T) * (np.abs(a + a.T) > 0.25))
    m = LocalMap(2, 0, 2, ids, kinds, x, info, "m")
    framed = to_feature_frame(m, (10, 11))
    assert sp.issparse(framed.info) == (x.size > DENSE_MAX)
    back = from_feature_frame(framed, 0, 2, "back")
    order_back, order = np.argsort(back.keys), np.argsort(m.keys)
    sc_back, sc = back.scalar_index(order_back), m.scalar_index(order)
    np.testing.assert_allclose(back.x[sc_back], m.x[sc], atol=1e-10)
    np.testing.assert_allclose(to_dense(back.info)[np.ix_(sc_back, sc_back)], to_dense(m.info)[np.ix_(sc, sc)],
                               rtol=1e-9, atol=1e-9)
