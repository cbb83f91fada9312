"""Islands and several robots through the installed node: a lost submap, two robots' streams."""

from __future__ import annotations

import numpy as np
import pytest
from geometry_msgs.msg import PoseWithCovarianceStamped
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from rclpy.serialization import serialize_message

from linear_slam_ros.evaluation.runner import run_join
from linear_slam_ros.evaluation.synthetic import make_world, noisy_local_maps
from linear_slam_ros.joiner.robots import ROBOT_ID_STRIDE
from linear_slam_ros.joiner.strategy import JoinMethod
from linear_slam_ros.ros.bagio import BagRecord
from linear_slam_ros.ros.spin import spin_until
from msg_adapters import Stamp, encode_map
from msg_adapters.ros import to_msg
from ros_support import wait_for_global_map


@pytest.fixture(scope="module")
def maps():
    world = make_world(2, 36, 40, np.random.default_rng(31))
    return noisy_local_maps(world, np.random.default_rng(32), steps_per_map=3)


def _records(topic: str, maps, seqs) -> list[BagRecord]:
    return [
        BagRecord(topic, 0, serialize_message(to_msg(encode_map(m, s, Stamp(s, 0)))), False)
        for m, s in zip(maps, seqs, strict=True)
    ]


def test_a_lost_submap_becomes_an_island_that_links_back(node, start_joiner, maps):
    joiner = start_joiner(reorder_timeout=0.5, publish_rate=20.0)
    seqs = [s for s in range(1, len(maps) + 1) if s != 4]  # seq 4 is lost on the way
    joiner.play(node, _records("local_map", [maps[s - 1] for s in seqs], seqs))
    final, _ = wait_for_global_map(node, joiner.topic("global_map"), lambda m: m.n_submaps == len(seqs), 30.0, joiner)
    code, output = joiner.stop()
    assert code == 0, output[-2000:]
    assert final.islands == (len(seqs),) and final.stats["n_islands"] == 1.0
    assert final.stats["n_rejected"] == 1.0  # the gap, counted once
    assert "starts island 1" in output and "links island 1" in output
    full = run_join(maps, JoinMethod.ONLINE_DC).result
    assert set(final.local_map.feature_ids.tolist()) == set(full.feature_ids.tolist())


def test_two_robots_publish_into_one_map(node, start_joiner, maps):
    half = len(maps) // 2
    joiner = start_joiner(robots="[a,b]", publish_rate=20.0)
    a = _records("a/local_map", maps[:half], range(1, half + 1))
    b = _records("b/local_map", maps[half:], range(1, len(maps) - half + 1))  # its own sequence numbers
    received: dict[str, PoseWithCovarianceStamped] = {}
    qos = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
    subs = [node.create_subscription(PoseWithCovarianceStamped, joiner.topic(f"{r}/pose"),
                                     lambda msg, r=r: received.__setitem__(r, msg), qos) for r in ("a", "b")]
    # robot b's pose named both by its own id and by its global id: refused, and its seq stays free for the valid one
    m = maps[half + 1]
    ids = m.ids.copy()
    ids[m.ids == m.end_id] = ROBOT_ID_STRIDE + m.frame_id  # its one pose: the end pose, named as the frame pose
    twice = _records("b/local_map", [m.replace(ids=ids, end_id=ROBOT_ID_STRIDE + m.frame_id)], [2])
    joiner.play(node, [r for pair in zip(a, b, strict=False) for r in pair][:3] + twice)
    joiner.play(node, [r for pair in zip(a, b, strict=False) for r in pair][3:] + a[len(b):] + b[len(a):])
    final, _ = wait_for_global_map(node, joiner.topic("global_map"), lambda m: m.n_submaps == len(maps), 30.0, joiner)
    assert spin_until(node, lambda: len(received) == 2, 10.0), sorted(received)
    code, output = joiner.stop()
    for sub in subs:
        node.destroy_subscription(sub)
    assert code == 0, output[-2000:]
    assert final.islands == (len(maps),) and final.stats["n_rejected"] == 1.0  # robot b's island met robot a's
    assert f"b/local_map rejected: robot slot 1: pose {m.frame_id} is given twice" in output
    b_poses = [int(p) for p in final.local_map.pose_ids if p >= ROBOT_ID_STRIDE]
    assert b_poses and min(b_poses) > ROBOT_ID_STRIDE  # robot b's poses, renamed
    assert received["b"].header.frame_id == "map"
