"""Shared fixtures of the pose-graph tests: a synthetic 2D graph of a robot driving circles."""

from __future__ import annotations

import numpy as np
import pytest

from linear_slam_ros.core.geometry import relative_pose, wrap_angle
from linear_slam_ros.evaluation.synthetic import World, make_world
from linear_slam_ros.pose_graph.graph import PoseGraph


def _circle_graph(rng, n=60, loops=3.0, per_loop=20, sigma=(0.0, 0.0)) -> tuple[World, PoseGraph]:
    """A robot driving ``loops`` circles: odometry edges and a loop closure to the same spot one lap earlier."""
    world = make_world(2, n, 0, rng, loops=loops)
    pairs = [(k, k + 1) for k in range(n)] + [(k, k + per_loop) for k in range(0, n - per_loop + 1, 2)]
    f, t, z, info = [], [], [], []
    for a, b in pairs:
        rel = relative_pose(2, world.poses[a], world.poses[b])
        noise = rng.normal(size=3) * np.array([sigma[0], sigma[0], sigma[1]])
        z.append(np.r_[rel[:2] + noise[:2], wrap_angle(rel[2] + noise[2])])
        f.append(a), t.append(b)
        s = np.array([max(sigma[0], 1e-3)] * 2 + [max(sigma[1], 1e-3)])
        info.append(np.diag(s**-2))
    return world, PoseGraph.from_edges(f, t, np.array(z), np.array(info))


@pytest.fixture
def circle_graph():
    """Return the builder ``circle_graph(rng, n=60, loops=3.0, per_loop=20, sigma=(0, 0)) -> (world, graph)``."""
    return _circle_graph


@pytest.fixture
def make_chunk():
    """Return ``make_chunk(**fields)``: a star chunk of two edges from pose 3, with fields overridden."""

    def make(**over):
        kw = dict(
            from_ids=np.array([3, 3]),
            to_ids=np.array([4, 7]),
            measurements=np.array([[1.0, 0, 0.1], [2.0, 1, -0.2]]),
            information=np.stack([np.eye(3), 2 * np.eye(3)]),
            dim=2,
            name="pose-graph chunk 1",
        )
        kw.update(over)
        return PoseGraph.from_edges(**kw)

    return make
