"""The node hands the refiner exactly what each join fused (``Joiner.on_fused``), with the submap's arrival."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from linear_slam_ros.core.local_map import POSE, LocalMap
from linear_slam_ros.ros.node import JoinerNode


def _map(frame: int, pose: int) -> LocalMap:
    return LocalMap(2, frame, pose, np.array([pose]), np.array([POSE], dtype=np.int8), np.zeros(3), np.eye(3))


def test_each_fused_measurement_is_submitted_once_with_its_submaps_arrival():
    submitted = []
    fake = SimpleNamespace(
        refiner=SimpleNamespace(submit=submitted.append), _refine_waiting={},
        _stamp=lambda: SimpleNamespace(sec=7, nanosec=5),
    )
    fake._refine_waiting.update({3: 1.5, ("b", 4): 2.5, 9: 3.0})
    JoinerNode._on_fused(fake, "", 3, (_map(2, 3), _map(0, 3)))  # type: ignore[arg-type]
    JoinerNode._on_fused(fake, "b", 4, (_map(3, 4),))  # type: ignore[arg-type]
    JoinerNode._on_fused(fake, "", 8, (_map(7, 8),))  # type: ignore[arg-type]
    assert [(s.seq, s.submap.frame_id, s.arrived, s.stamp, s.extra) for s in submitted] == [
        (3, 2, 1.5, (7, 5), False), (3, 0, 1.5, (7, 5), True), (4, 3, 2.5, (7, 5), False)]
    assert fake._refine_waiting == {9: 3.0}  # taken; 8 had no arrival (joined before the refiner started)
    JoinerNode._on_fused(SimpleNamespace(refiner=None, _refine_waiting={5: 1.0}), "", 5, (_map(4, 5),))  # type: ignore[arg-type]
    assert len(submitted) == 3  # no refiner: nothing sent
