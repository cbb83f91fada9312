"""The joiner's newest-pose outputs through the installed node: ``pose`` with its covariance, TF, the TUM file.

One joiner process joins 8 seeded synthetic local maps (stamped); the test checks the latched
``pose`` (a PoseWithCovarianceStamped in ``map_frame``) against the offline joined map's end
pose and its exact marginal covariance, then ``~/save_map``'s ``poses.tum``. TF: with
``publish_tf`` the node broadcasts ``map_frame`` -> ``base_frame`` on ``/tf``; a subscriber on
``/tf`` checks it where ``tf2_msgs`` is installed (a ROS 2 install). The PyPI wheels this
machine uses have no tf2 package at all, so here the node must say at start-up that it
publishes no TF, and still join and publish ``pose``.
"""

from __future__ import annotations

import time

import numpy as np
import pytest
from geometry_msgs.msg import PoseWithCovarianceStamped
from rclpy.executors import SingleThreadedExecutor
from rclpy.serialization import serialize_message

from linear_slam_ros.core.frames import change_frame
from linear_slam_ros.core.local_map import pose_key, to_dense
from linear_slam_ros.evaluation.runner import run_join
from linear_slam_ros.evaluation.synthetic import make_world, noisy_local_maps
from linear_slam_ros.ros.bagio import BagRecord
from linear_slam_ros.ros.player import play
from linear_slam_ros.ros.qos import latched_qos
from linear_slam_ros.ros.tf_output import tf_message_class
from msg_adapters import Stamp, encode_map
from msg_adapters.ros import to_msg
from msg_adapters.views import ROS_POSE_ORDER
from ros_support import call_trigger, wait_for_global_map

N_MAPS = 8
STAMPS = [Stamp(1_700_000_000 + i, 250_000_000 * (i % 4)) for i in range(1, N_MAPS + 1)]


def _maps():
    world = make_world(2, 4 * N_MAPS, 25, np.random.default_rng(31))
    return noisy_local_maps(world, np.random.default_rng(32), steps_per_map=4)


def _run_stream(node, joiner, maps) -> None:
    messages = [to_msg(encode_map(m, i, STAMPS[i - 1])) for i, m in enumerate(maps, start=1)]
    records = [BagRecord(joiner.topic("local_map"), 0, serialize_message(m), False) for m in messages]
    play(node, records, rate_factor=0.0, wait_s=30.0)
    wait_for_global_map(node, joiner.topic("global_map"), lambda m: m.n_submaps == len(maps), 60.0, joiner)


def _latest(node, msg_type, topic: str, done, timeout_s: float = 20.0, qos=None):
    """Spin until a message on ``topic`` satisfies ``done``; return it (``None``: none did)."""
    got: list = []
    sub = node.create_subscription(msg_type, topic, got.append, qos or latched_qos())
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    deadline = time.monotonic() + timeout_s
    try:
        while time.monotonic() < deadline:
            executor.spin_once(timeout_sec=0.1)
            if got and done(got[-1]):
                return got[-1]
    finally:
        executor.remove_node(node)
        node.destroy_subscription(sub)
    return None


def _stamp_of(msg) -> tuple[int, int]:
    return msg.header.stamp.sec, msg.header.stamp.nanosec


def _offline_end_pose(maps):
    """The end pose of the offline joined map in the first pose's frame, and its marginal covariance (dense inverse)."""
    joined = run_join(maps, "online-dc").result
    first = maps[0].frame_id
    moved = change_frame(joined, first)
    sc = moved.scalar_index([moved.key_set[pose_key(joined.end_id)]])
    return moved.x[sc], np.linalg.inv(to_dense(moved.info))[np.ix_(sc, sc)]


def test_pose_carries_the_exact_covariance_and_save_map_writes_tum(node, start_joiner, tmp_path):
    maps = _maps()
    saved = tmp_path / "saved"
    joiner = start_joiner(publish_rate=20.0, map_frame="world", save_directory=str(saved))
    _run_stream(node, joiner, maps)
    pose_expected, cov_expected = _offline_end_pose(maps)
    rows = list(ROS_POSE_ORDER[2])

    def exact(msg) -> bool:  # the global map's pose: the exact covariance of the offline map's end pose
        cov = np.array(msg.pose.covariance).reshape(6, 6)
        return bool(np.allclose(cov[np.ix_(rows, rows)], cov_expected, rtol=1e-5, atol=1e-12))

    msg = _latest(node, PoseWithCovarianceStamped, joiner.topic("pose"), exact)
    assert msg is not None, "no pose with the exact covariance of the joined map's end pose"
    assert msg.header.frame_id == "world"
    assert (msg.header.stamp.sec, msg.header.stamp.nanosec) == (STAMPS[-1].sec, STAMPS[-1].nanosec)
    assert msg.pose.pose.position.x == pytest.approx(pose_expected[0], abs=1e-9)
    assert msg.pose.pose.position.y == pytest.approx(pose_expected[1], abs=1e-9)
    yaw = 2.0 * np.arctan2(msg.pose.pose.orientation.z, msg.pose.pose.orientation.w)
    assert np.remainder(yaw - pose_expected[2] + np.pi, 2 * np.pi) - np.pi == pytest.approx(0.0, abs=1e-9)
    cov = np.array(msg.pose.covariance).reshape(6, 6)
    assert np.all(cov[2:5, :] == 0.0) and np.all(cov[:, 2:5] == 0.0)  # z, roll, pitch: fixed in 2D

    result = call_trigger(node, f"/{joiner.namespace}/joiner/save_map")
    assert result.success, result.message
    lines = [ln.split() for ln in (saved / "poses.tum").read_text().splitlines() if not ln.startswith("#")]
    assert len(lines) == N_MAPS  # one per submap end pose, stamped with its submap's stamp
    assert [float(ln[0]) for ln in lines] == pytest.approx([s.sec + s.nanosec * 1e-9 for s in STAMPS], abs=1e-9)
    assert all(len(ln) == 8 for ln in lines)
    last = np.array(lines[-1][1:], dtype=float)
    assert last[:2] == pytest.approx(pose_expected[:2], abs=1e-9) and last[2] == 0.0
    assert np.linalg.norm(last[3:]) == pytest.approx(1.0) and last[6] >= 0.0
    code, output = joiner.stop()
    assert code == 0, output[-3000:]


def test_publish_tf_broadcasts_the_newest_pose_or_says_why_not(node, start_joiner):
    """Where tf2_msgs is installed: one map -> robot transform per stamp, in stamp order, the first pose
    published at that stamp (TF listeners take a repeated stamp as a publisher error)."""
    maps = _maps()
    joiner = start_joiner(publish_rate=20.0, publish_tf=True, base_frame="robot")
    tf_class = tf_message_class()
    received: list = []
    poses: list = []
    if tf_class is not None:  # a ROS 2 install: listen on /tf and pose before the stream starts
        node.create_subscription(tf_class, "/tf", received.append, 100)
        node.create_subscription(PoseWithCovarianceStamped, joiner.topic("pose"), poses.append, 100)
    _run_stream(node, joiner, maps)
    if tf_class is not None:
        last = (STAMPS[-1].sec, STAMPS[-1].nanosec)
        deadline = time.monotonic() + 20.0
        executor = SingleThreadedExecutor()
        executor.add_node(node)

        def ours() -> list:
            return [t for msg in received for t in msg.transforms if (t.header.frame_id, t.child_frame_id) == ("map", "robot")]

        while time.monotonic() < deadline and not any(_stamp_of(t) == last for t in ours()):
            executor.spin_once(timeout_sec=0.1)
        executor.spin_once(timeout_sec=0.5)  # what the global map would have sent at that stamp too
        executor.remove_node(node)
        transforms = ours()
        stamps = [_stamp_of(t) for t in transforms]
        assert stamps and stamps[-1] == last, "no map -> robot transform at the last submap's stamp on /tf"
        assert stamps == sorted(set(stamps)), "a stamp went to /tf twice, or out of order"
        first_pose = next(p for p in poses if _stamp_of(p) == last)
        t = transforms[-1].transform.translation
        assert (t.x, t.y) == pytest.approx((first_pose.pose.pose.position.x, first_pose.pose.pose.position.y), abs=1e-12)
    code, output = joiner.stop()
    assert code == 0
    if tf_class is None:
        assert "publish_tf is set but no TF is published: neither tf2_ros nor tf2_msgs can be imported" in output
