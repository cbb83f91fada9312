"""The node's per-submap records, with the node in this process (no DDS peer): submaps joined by the reorder
timeout, a loaded map, several robots' poses from an older global map."""

from __future__ import annotations

import time
import uuid

import numpy as np
import pytest
from rclpy.parameter import Parameter
from rclpy.serialization import serialize_message
from std_srvs.srv import Trigger

import ros_support  # noqa: F401  (DDS on loopback, in this run's domain)
from linear_slam_ros.evaluation.synthetic import make_world, noisy_local_maps
from linear_slam_ros.ros import node as node_module
from msg_adapters import Stamp, encode_map
from msg_adapters.ros import to_msg


@pytest.fixture(scope="module")
def maps():
    world = make_world(2, 32, 25, np.random.default_rng(31))
    return noisy_local_maps(world, np.random.default_rng(32), steps_per_map=4)


def _raw(local_map, seq: int, stamp: Stamp) -> bytes:
    return serialize_message(to_msg(encode_map(local_map, seq, stamp)))


@pytest.fixture
def make_node(rclpy_session, monkeypatch):
    monkeypatch.setattr(node_module, "tune_allocator", lambda threshold: True)  # this process's allocator as it is
    made = []

    def make(**params):
        overrides = [Parameter(k, value=v) for k, v in params.items()]
        node = node_module.JoinerNode(namespace=f"t{uuid.uuid4().hex[:8]}", parameter_overrides=overrides)
        sent: list[tuple[str, np.ndarray, tuple[int, int]]] = []
        send = node._send_pose

        def spy(pose, cov, stamp, robot=""):
            sent.append((robot, np.array(pose), (stamp.sec, stamp.nanosec)))
            send(pose, cov, stamp, robot)

        node._send_pose = spy
        made.append(node)
        return node, sent

    yield make
    for node in made:
        node.destroy_node()


def _trigger(handler):
    return handler(Trigger.Request(), Trigger.Response())


def test_submaps_joined_by_the_reorder_timeout_are_recorded_as_on_arrival(make_node, maps, tmp_path):
    node, sent = make_node(reorder_timeout=0.5, save_directory=str(tmp_path))
    for seq in (1, 2, 4, 5):  # 3 is lost
        node._receive("local_map", _raw(maps[seq - 1], seq, Stamp(1000 + seq, 0)))
    node._flush_poses()
    assert node.joiner.state.n_joined == 2
    before = len(sent)
    time.sleep(0.6)
    node._on_expire_timer()
    assert node.joiner.state.n_joined == 4
    assert len(sent) == before + 1 and sent[-1][0] == ""  # the newest pose, at once
    assert node._output_stamp == Stamp(1005, 0) and not node._data_stamps  # the outputs carry 5's stamp
    assert sorted(node._poses.pose_stamps.values()) == [1001.0, 1002.0, 1004.0, 1005.0]  # poses.tum has them


def test_a_loaded_map_replaces_the_records_of_the_map_it_replaces(make_node, maps, tmp_path):
    node, sent = make_node(save_directory=str(tmp_path / "a"))
    for seq in (1, 2, 3):
        node._receive("local_map", _raw(maps[seq - 1], seq, Stamp(1000 + seq, 0)))
    node._flush_poses()
    assert _trigger(node._on_save_map).success
    assert _trigger(node._on_reset).success
    for seq in range(1, 9):  # another map, with other stamps and more submaps
        node._receive("local_map", _raw(maps[seq - 1], seq, Stamp(9000 + seq, 0)))
    node._flush_poses()
    node.set_parameters([Parameter("load_path", value=str(tmp_path / "a" / "state.npz"))])
    before = len(sent)
    assert _trigger(node._on_load_map).success  # publishes the loaded map at once
    assert node.joiner.state.n_joined == 3
    assert len(sent) > before  # the loaded map's newest pose went out (the 8-submap map's no longer blocks it)
    assert node._output_stamp is None and node._poses.pose_stamps == {}  # a loaded map's poses have no stamp


def test_a_global_map_of_an_older_state_does_not_overwrite_a_robot_s_newer_pose(make_node, maps, monkeypatch):
    built = node_module.global_result

    def slow(state, frame):  # a large map: its build outlasts the next arrivals
        time.sleep(0.5)
        return built(state, frame)

    monkeypatch.setattr(node_module, "global_result", slow)
    node, sent = make_node(robots=["a"])
    node._receive("a/local_map", _raw(maps[0], 1, Stamp(1, 0)), "a")
    node._flush_poses()
    node._outputs.wake()
    time.sleep(0.2)  # the output thread builds the map of the 1-submap state
    for seq in range(2, 6):
        node._receive("a/local_map", _raw(maps[seq - 1], seq, Stamp(seq, 0)), "a")
        node._flush_poses()
    newest = sent[-1][1]
    time.sleep(1.5)  # that map's publication, and the next one's
    robot_a = [pose for robot, pose, _ in sent if robot == "a"]
    np.testing.assert_allclose(robot_a[-1], newest, atol=0.5)  # never back to the first submap's pose
    assert not np.allclose(robot_a[-1], robot_a[0], atol=0.5)
