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
from support import wait_until


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
    assert sorted(node._poses.pose_stamps.values()) == [s * 10**9 for s in (1001, 1002, 1004, 1005)]  # path, poses.tum


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


def test_tf_goes_out_once_per_stamp_and_to_odom_with_odom_frame(make_node, maps, monkeypatch):
    """The arrival's pose and the global map's of the same submap both went to /tf with one stamp (review of
    session 26); with ``odom_frame`` the node sends map -> odom (REP-105), composed with the odometry."""
    from geometry_msgs.msg import TransformStamped

    from linear_slam_ros.ros.tf_output import map_to_odom
    from msg_adapters.views import transform_msg

    transforms: list[TransformStamped] = []
    monkeypatch.setattr(node_module, "tf_sender", lambda node: (transforms.append, "a test sender"))
    def lookup(odom_frame, base_frame, stamp):
        assert (odom_frame, base_frame) == ("odom", "robot")
        return odom_base

    monkeypatch.setattr(node_module, "odom_lookup", lambda: (lookup, "a test lookup"))
    odom_base = transform_msg(2, np.array([0.5, -1.0, 0.2]), "odom", "robot", Stamp(0, 0))
    for odom_frame in ("", "odom"):
        transforms.clear()
        node, sent = make_node(publish_tf=True, base_frame="robot", odom_frame=odom_frame, publish_rate=50.0,
                               tf_publish_period=0.0)  # with each pose only (re-sends: the next test)
        for seq in range(1, 7):
            node._receive("local_map", _raw(maps[seq - 1], seq, Stamp(1000 + seq, 0)), "")
            node._flush_poses()
            assert wait_until(lambda s=seq, sent=sent: sum(1 for _, _, st in sent if st == (1000 + s, 0)) >= 2)  # arrival + map
        stamps = [(t.header.stamp.sec, t.header.stamp.nanosec) for t in transforms]
        assert stamps == [(1000 + seq, 0) for seq in range(1, 7)]  # each stamp once, in order
        assert {(t.header.frame_id, t.child_frame_id) for t in transforms} == {("map", odom_frame or "robot")}
        for t in transforms:  # the first pose sent at that stamp (the arrival's)
            first = next(pose for _, pose, st in sent if st == (t.header.stamp.sec, t.header.stamp.nanosec))
            expected = transform_msg(2, first, "map", "robot", t.header.stamp)
            if odom_frame:
                expected = map_to_odom(expected, odom_base)
            for got, want in ((t.transform.translation, expected.transform.translation),
                              (t.transform.rotation, expected.transform.rotation)):
                np.testing.assert_allclose([got.x, got.y, got.z], [want.x, want.y, want.z], atol=1e-12)


def test_map_to_odom_is_sent_again_ahead_of_the_node_clock_between_submaps(make_node, maps, monkeypatch):
    from geometry_msgs.msg import TransformStamped

    from msg_adapters.views import transform_msg

    transforms: list[TransformStamped] = []
    monkeypatch.setattr(node_module, "tf_sender", lambda node: (transforms.append, "a test sender"))
    odom_base = transform_msg(2, np.array([0.5, -1.0, 0.2]), "odom", "robot", Stamp(0, 0))
    monkeypatch.setattr(node_module, "odom_lookup", lambda: (lambda odom, base, stamp: odom_base, "a test lookup"))
    node, _ = make_node(publish_tf=True, base_frame="robot", odom_frame="odom", tf_publish_period=0.05)
    time.sleep(0.2)
    assert transforms == []  # nothing to send again before the first pose
    node._receive("local_map", _raw(maps[0], 1, Stamp(1000, 0)), "")
    node._flush_poses()
    assert wait_until(lambda: len(transforms) >= 4, 5.0)
    first, *again = transforms[:4]
    assert (first.header.stamp.sec, first.header.stamp.nanosec) == (1000, 0)  # the pose's own
    now = node.get_clock().now().nanoseconds
    stamps = [t.header.stamp.sec * 10**9 + t.header.stamp.nanosec for t in again]
    assert stamps == sorted(set(stamps)) and now - 2 * 10**9 < stamps[0] <= now + 0.05e9  # ahead of the clock, once each
    assert all((t.header.frame_id, t.child_frame_id, t.transform) == ("map", "odom", first.transform) for t in again)
    node.destroy_node()
    stopped = len(transforms)
    time.sleep(0.2)
    assert len(transforms) == stopped  # the re-sending thread ended with the node


def test_without_an_odometry_buffer_odom_frame_sends_no_tf(make_node, monkeypatch):
    monkeypatch.setattr(node_module, "tf_sender", lambda node: (print, "a test sender"))
    monkeypatch.setattr(node_module, "odom_lookup", lambda: (None, "odom_frame needs tf2_ros (its buffer)"))
    node, _ = make_node(publish_tf=True, odom_frame="odom")
    assert node._tf is None


def test_odom_lookup_gives_its_listener_a_node_of_its_own(monkeypatch):
    """tf2_ros's listener with ``spin_thread`` adds its node to an executor of its own: given the joiner's node, that
    would take the node from the joiner's executor. A stand-in module records the calls (tf2 is not on PyPI)."""
    import importlib.util
    import sys
    import types

    from linear_slam_ros.ros.tf_output import odom_lookup

    if importlib.util.find_spec("tf2_ros") is None:  # the PyPI wheels: no tf2 package
        assert odom_lookup() == (None, "odom_frame needs tf2_ros (its buffer), which cannot be imported")
    calls: list = []

    class Buffer:
        def lookup_transform(self, target, source, time, timeout):
            calls.append(("lookup", target, source, time.nanoseconds, timeout.nanoseconds))
            return "the transform"

    class TransformListener:
        def __init__(self, buffer, node, *, spin_thread=False):
            calls.append(("listener", node, spin_thread))

    monkeypatch.setitem(sys.modules, "tf2_ros", types.SimpleNamespace(Buffer=Buffer, TransformListener=TransformListener))
    lookup, how = odom_lookup()
    assert how == "tf2_ros buffer" and calls == [("listener", None, True)]
    from builtin_interfaces.msg import Time

    assert lookup("odom", "base_link", Time(sec=3, nanosec=5)) == "the transform"
    assert calls[-1] == ("lookup", "odom", "base_link", 3_000_000_005, 0)  # at the pose's stamp, without waiting


class _Latched:
    def __init__(self) -> None:
        self.messages: list = []

    def publish(self, msg) -> None:
        self.messages.append(msg)


def test_reset_replaces_the_latched_pose_by_an_unknown_one(make_node, maps):
    """After ``~/reset`` a late subscriber got the cleared map's pose and covariance beside an empty map
    (review of session 26)."""
    node, sent = make_node(publish_rate=50.0)
    latched = node._pose_pubs[""] = _Latched()
    for seq in (1, 2, 3):
        node._receive("local_map", _raw(maps[seq - 1], seq, Stamp(1000 + seq, 0)), "")
        node._flush_poses()
    assert wait_until(lambda: len(latched.messages) >= 4 and latched.messages[-1].pose.covariance[0] > 0.0)  # the map's
    assert _trigger(node._on_reset).success
    assert wait_until(lambda: latched.messages[-1].pose.covariance[0] == -1.0)
    cleared = latched.messages[-1]
    assert not np.array(cleared.pose.covariance)[1:].any() and cleared.header.frame_id == "map"
    p, q = cleared.pose.pose.position, cleared.pose.pose.orientation
    assert (p.x, p.y, p.z, q.x, q.y, q.z, q.w) == (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0)
    n = len(latched.messages)
    time.sleep(0.3)  # said once, not at every publication of the empty map
    assert len(latched.messages) == n


def test_feature_only_views_keep_the_frame_of_the_first_map_viewed(make_node):
    """The global feature-only map's frame features change at merges: drawn in its own frame, the whole map
    moved 100 m and more at every update (review of session 26)."""
    from linear_slam_ros.feature_only.frames import change_feature_frame
    from linear_slam_ros.feature_only.maps import FeatureMap

    fmap = _feature_map(np.random.default_rng(5))
    node, _ = make_node(map_type="feature-only")
    assert node._in_view_frame(fmap) is fmap
    other = change_feature_frame(fmap, fmap.ids[:2].tolist())
    drawn = node._in_view_frame(other)
    assert drawn.frame_ids == fmap.frame_ids
    for fid, position in fmap.positions().items():
        np.testing.assert_allclose(drawn.positions()[fid], position, atol=1e-9)
    stranger = FeatureMap(2, (10**6, 10**6 + 1), np.zeros(0, dtype=np.int64), np.array([3.0]), np.eye(1))
    assert node._in_view_frame(stranger) is stranger  # the first frame's features are gone: its own frame from now on
    assert node._view_frame == stranger.frame_ids
    assert _trigger(node._on_reset).success and node._view_frame is None


def _feature_map(rng):
    from linear_slam_ros.feature_only.conversion import to_feature_only
    from linear_slam_ros.feature_only.joining import join_features_sequential
    from linear_slam_ros.feature_only.precondition import precondition

    world = make_world(2, 12, 20, rng)
    groups = precondition(noisy_local_maps(world, rng, steps_per_map=4, sensor_range=9))
    return join_features_sequential([to_feature_only(g) for g in groups])


def test_the_path_carries_each_joined_submap_s_stamp_on_its_end_pose(make_node, maps):
    node, _ = make_node()
    for seq in (1, 2, 3):
        node._receive("local_map", _raw(maps[seq - 1], seq, Stamp(1000 + seq, 7)), "")
    node._flush_poses()
    state = node.joiner.state
    views = node._map_views(node_module.global_result(state, "first_pose"), state, node._stamp_msg())
    by_pose = {round(p.pose.position.x, 9): (p.header.stamp.sec, p.header.stamp.nanosec) for p in views.path.poses}
    ends = [maps[k].end_id for k in range(3)]
    first = node_module.global_result(state, "first_pose")
    for k, end in enumerate(ends):
        assert by_pose[round(float(first.pose(end)[0]), 9)] == (1001 + k, 7)


def test_a_journal_record_that_no_longer_decodes_stops_the_start(make_node, maps, tmp_path):
    """Restarted without the robots it journaled, the node refused robot b's records one by one, and the next
    snapshot counted them: they were lost for good, also once started again with the right list."""
    from linear_slam_ros.core.errors import ConfigError
    from linear_slam_ros.ros.persistence import StateStore

    store = StateStore(tmp_path / "state")
    journal = store.open_journal(0)
    for seq in (1, 2):
        journal.append("b/local_map", _raw(maps[seq - 1], seq, Stamp(seq, 0)), 0)
    store.close()  # a kill -9 before any snapshot: both records to replay
    with pytest.raises(ConfigError, match=r"journal record 0 \(b/local_map\) of .*/state/journal no longer decodes: robot 'b' "
                                          r"is not in robots=\[\]; start with the robots and input limits it was journaled "
                                          r"with, .*\(or the record is damaged: the journal keeps no checksum per record\)$"):
        make_node(state_dir=str(tmp_path / "state"))
    node, _ = make_node(state_dir=str(tmp_path / "state"), robots=["a", "b"])  # as journaled: both come back
    assert node.joiner.state.n_joined == 2


def test_the_journal_is_synced_while_a_long_publication_holds_the_output_thread(make_node, maps, tmp_path, monkeypatch):
    """Behind publications of seconds (a large map) on the output thread, the journal's fsyncs came 2-3 s apart."""
    def slow_publication(self) -> None:
        time.sleep(4.0)

    monkeypatch.setattr(node_module.JoinerNode, "_on_publish_timer", slow_publication)
    node, _ = make_node(state_dir=str(tmp_path / "state"))
    time.sleep(0.2)  # the output thread is in its first publication now
    node._receive("local_map", _raw(maps[0], 1, Stamp(1, 0)))
    journal = node.store.journal
    assert journal._unsynced == 1
    t0 = time.monotonic()
    assert wait_until(lambda: journal._unsynced == 0, 3.0), "not synced while the output thread was busy"
    assert time.monotonic() - t0 < 1.6  # fsync_period_s 1 s, checked every 0.25 s


def test_a_gap_given_up_by_the_reorder_timeout_is_snapshotted_at_once(make_node, maps, tmp_path):
    """No journal record holds that decision: a restart waited for the number again and joined it when it came late,
    where the run before the kill had skipped it."""
    node, _ = make_node(reorder_timeout=0.3, state_dir=str(tmp_path / "state"), snapshot_period=1000)
    for seq in (1, 2, 4):  # 3 is lost
        node._receive("local_map", _raw(maps[seq - 1], seq, Stamp(seq, 0)))
    assert wait_until(lambda: node.store.snapshots() != [], 1.0) is False  # none due: 2 of 1000 joined
    node._on_expire_timer()  # (no executor spins here) 3 is given up
    assert node.joiner.state.n_joined == 3
    assert wait_until(lambda: [n for n, _ in node.store.snapshots()] == [3], 2.0), node.store.snapshots()


@pytest.mark.parametrize("other", ["mode", "robots"])
def test_a_load_map_refused_leaves_the_old_map_to_resume_from(make_node, maps, tmp_path, monkeypatch, other):
    """The start of the loaded map was recorded (start.json, the old snapshots deleted) before the restore refused it:
    after a crash the next start took the refused file again and could not start (the old map was lost)."""
    from linear_slam_ros.joiner.joiner import Joiner
    from linear_slam_ros.joiner.robots import qualify
    from linear_slam_ros.joiner.snapshot import write_snapshot
    from linear_slam_ros.joiner.strategy import JoinMethod

    if other == "mode":
        foreign = Joiner(JoinMethod.SEQUENTIAL)
        foreign.offer(maps[0], 1)
        expected = "mode='sequential'"
    else:
        foreign = Joiner(JoinMethod.ONLINE_DC, robots=("b", "a"))
        foreign.offer(maps[0], 1, "b")
        foreign.offer(qualify(maps[5], 1), 1, "a")
        expected = r"robots=['b', 'a'], this joiner runs robots=['a', 'b']"
    write_snapshot(tmp_path / "foreign.npz", foreign.save())
    state_dir = str(tmp_path / "state")
    node, _ = make_node(state_dir=state_dir, robots=["a", "b"])
    for seq in (1, 2, 3):
        node._receive("a/local_map", _raw(maps[seq - 1], seq, Stamp(1000 + seq, 0)), "a")
    node._flush_poses()
    node.set_parameters([Parameter("load_path", value=str(tmp_path / "foreign.npz"))])
    response = _trigger(node._on_load_map)
    assert not response.success and expected in response.message, response.message
    assert node.joiner.state.n_joined == 3
    monkeypatch.setattr(node, "_snapshot", lambda: None)  # a crash: no final snapshot, the journal alone
    node.destroy_node()
    again, _ = make_node(state_dir=state_dir, robots=["a", "b"])
    assert again.joiner.state.n_joined == 3  # the old map, resumed
