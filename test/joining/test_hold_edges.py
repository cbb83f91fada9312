"""Held closures at their edges: a chain whose ids run down, a held pose cut out of its submap, a submap of held
closures only. (Found by a mutation audit: each test fails on a mutant the suite let through.)
"""

from __future__ import annotations

import numpy as np

from linear_slam_ros.core.local_map import FEATURE, POSE, LocalMap
from linear_slam_ros.joining.hold import split_forward, without_held


def test_a_chain_whose_ids_run_down_holds_nothing_of_its_own_path():
    # frame pose 10, end pose 7: poses 8 and 9 lie on its own path (ids run down the trajectory)
    x = np.arange(9, dtype=float) * 0.1
    m = LocalMap(2, 10, 7, np.array([7, 8, 9]), np.full(3, POSE, np.int8), x, np.eye(9) * 10.0)
    rest, held = split_forward(m, lambda key: False, 1)
    assert held == () and rest is m



def test_without_held_cuts_the_held_pose_only():
    x = np.arange(10, dtype=float) * 0.1
    kinds = np.array([POSE, POSE, FEATURE, FEATURE], np.int8)
    m = LocalMap(2, 5, 6, np.array([6, 40, 40, 41]), kinds, x, np.eye(10) * 10.0)
    _, held = split_forward(m, lambda key: False, 3)
    assert [h.target for h in held] == [40]
    (out,) = without_held([m], [("", 3)], held)
    assert list(zip(out.ids.tolist(), out.kinds.tolist(), strict=True)) == [(6, POSE), (40, FEATURE), (41, FEATURE)]


def test_a_submap_of_held_closures_only_is_dropped():
    x = np.arange(3, dtype=float) * 0.1
    m = LocalMap(2, 5, 6, np.array([6]), np.array([POSE], np.int8), x, np.eye(3) * 10.0)
    closure_only = LocalMap(2, 5, None, np.array([40]), np.array([POSE], np.int8), x, np.eye(3) * 10.0)
    from linear_slam_ros.joining.hold import HeldClosure
    h = HeldClosure(2, "", "c", 40, 5, closure_only)
    assert len(without_held([m, closure_only], [("", 1), ("", 2)], [h])) == 1
