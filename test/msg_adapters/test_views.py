"""Pose, covariance and transform conversions of msg_adapters.views, by their definitions."""

from __future__ import annotations

import numpy as np
import pytest
from builtin_interfaces.msg import Time
from scipy.spatial.transform import Rotation

from linear_slam_ros.core.geometry import rot3
from msg_adapters.views import pose_with_covariance_msg, ros_pose_covariance, transform_msg

STAMP = Time(sec=12, nanosec=345)


def _spd(n: int, rng: np.random.Generator) -> np.ndarray:
    a = rng.normal(size=(n, n))
    return a @ a.T + n * np.eye(n)


def test_2d_covariance_fills_x_y_yaw_and_leaves_z_roll_pitch_zero(rng):
    cov = _spd(3, rng)
    out = ros_pose_covariance(2, cov).reshape(6, 6)
    rows = [0, 1, 5]
    np.testing.assert_array_equal(out[np.ix_(rows, rows)], cov)
    out[np.ix_(rows, rows)] = 0.0
    assert not out.any()


def test_3d_covariance_is_reordered_to_roll_pitch_yaw(rng):
    cov = _spd(6, rng)  # x y z alpha beta gamma: alpha is the yaw, gamma the roll
    out = ros_pose_covariance(3, cov).reshape(6, 6)
    np.testing.assert_array_equal(out[:3, :3], cov[:3, :3])
    assert out[5, 5] == cov[3, 3] and out[4, 4] == cov[4, 4] and out[3, 3] == cov[5, 5]
    assert out[0, 5] == cov[0, 3] and out[3, 5] == cov[5, 3]
    np.testing.assert_array_equal(out, out.T)


def test_3d_angles_are_ros_yaw_pitch_roll(rng):
    pose = np.array([1.0, -2.0, 0.5, 0.3, -0.2, 0.1])
    msg = pose_with_covariance_msg(3, pose, _spd(6, rng), "map", STAMP)
    q = msg.pose.pose.orientation
    rot = Rotation.from_quat([q.x, q.y, q.z, q.w])
    np.testing.assert_allclose(rot.as_matrix(), rot3(pose[3:]).T, atol=1e-15)
    np.testing.assert_allclose(rot.as_euler("ZYX"), pose[3:], atol=1e-14)  # [yaw, pitch, roll] = [alpha, beta, gamma]


def test_pose_with_covariance_message_and_unknown_covariance(rng):
    cov = _spd(3, rng)
    msg = pose_with_covariance_msg(2, np.array([1.0, 2.0, 0.5]), cov, "world", STAMP)
    assert msg.header.frame_id == "world" and (msg.header.stamp.sec, msg.header.stamp.nanosec) == (12, 345)
    assert (msg.pose.pose.position.x, msg.pose.pose.position.y, msg.pose.pose.position.z) == (1.0, 2.0, 0.0)
    assert 2.0 * np.arctan2(msg.pose.pose.orientation.z, msg.pose.pose.orientation.w) == pytest.approx(0.5)
    assert np.array(msg.pose.covariance).reshape(6, 6)[5, 5] == cov[2, 2]
    unknown = pose_with_covariance_msg(2, np.zeros(3), None, "world", STAMP)
    assert unknown.pose.covariance[0] == -1.0 and not np.array(unknown.pose.covariance)[1:].any()


def test_transform_maps_child_coordinates_into_the_parent_frame():
    pose = np.array([3.0, 4.0, np.pi / 2])  # the robot at (3, 4) facing +y
    t = transform_msg(2, pose, "map", "base_link", STAMP)
    assert (t.header.frame_id, t.child_frame_id) == ("map", "base_link")
    assert (t.header.stamp.sec, t.header.stamp.nanosec) == (12, 345)
    r = t.transform.rotation
    ahead = Rotation.from_quat([r.x, r.y, r.z, r.w]).apply([1.0, 0.0, 0.0])  # 1 m ahead of the robot
    tr = t.transform.translation
    np.testing.assert_allclose(ahead + [tr.x, tr.y, tr.z], [3.0, 5.0, 0.0], atol=1e-15)


def test_feature_markers_have_distinct_ids_when_feature_ids_exceed_int32():
    """Robot 1's feature 7 is 2**32 + 7: as ``Marker.id`` (int32) it would wrap onto robot 0's feature 7."""
    from msg_adapters.views import point_markers

    ids = [7, 2**32 + 7, 2**40 + 3]
    points = {fid: np.array([float(k), 1.0]) for k, fid in enumerate(ids)}
    covariances = {fid: np.diag([0.1 * (k + 1), 0.2]) for k, fid in enumerate(ids)}
    markers = point_markers(2, points, "map", STAMP, covariances).markers
    ellipses = [m for m in markers if m.ns == "covariance"]
    assert [m.id for m in ellipses] == [0, 1, 2]
    assert [int(m.text) for m in ellipses] == ids
    assert [m.pose.position.x for m in ellipses] == [0.0, 1.0, 2.0]
    assert markers[0].action == markers[0].DELETEALL


def test_the_deleteall_of_a_marker_array_has_no_namespace():
    """RViz 2 deletes only a DELETEALL's namespace when it has one: the ellipses (``covariance``) of an earlier
    array stayed on screen once the map passed ``ellipse_max_state`` (review of session 26)."""
    from msg_adapters.views import empty_views, point_markers

    points = {3: np.array([1.0, 2.0]), 4: np.array([3.0, 4.0])}
    arrays = [point_markers(2, points, "map", STAMP, {3: np.eye(2), 4: np.eye(2)}), empty_views("map", STAMP).markers]
    for array in arrays:
        deletes = [m for m in array.markers if m.action == m.DELETEALL]
        assert [m.ns for m in deletes] == [""] and array.markers[0] is deletes[0]


def test_ellipses_of_zero_variance_are_drawn_thin_not_with_a_zero_scale():
    """A feature-only map's frame features have zero variance along their fixed coordinates; RViz refuses a
    marker with a zero scale."""
    from msg_adapters.views import MIN_MARKER_SCALE, point_markers

    points = {1: np.zeros(2), 2: np.array([5.0, 0.0]), 3: np.array([1.0, 1.0])}
    covariances = {1: np.zeros((2, 2)), 2: np.diag([0.0, 0.25]), 3: np.diag([0.04, 0.09])}
    ellipses = [m for m in point_markers(2, points, "map", STAMP, covariances).markers if m.ns == "covariance"]
    scales = [sorted((m.scale.x, m.scale.y)) for m in ellipses]
    assert scales[0] == [MIN_MARKER_SCALE, MIN_MARKER_SCALE]
    assert scales[1] == [MIN_MARKER_SCALE, pytest.approx(4.0 * 0.5)]  # full axis: 2 * 2 sigma
    assert scales[2] == [pytest.approx(4.0 * 0.2), pytest.approx(4.0 * 0.3)]


def test_path_poses_carry_their_own_stamps_where_known(rng):
    """evo and other trajectory tools read each PoseStamped's stamp from a recorded ``path``."""
    from linear_slam_ros.core.local_map import LocalMap
    from msg_adapters.views import map_views, path_msg

    ids = np.array([9, 1, 4, 2, 7])  # poses after the frame pose 0, not in id order
    joined = LocalMap(2, 0, 7, ids, np.zeros(5, dtype=np.int8), rng.normal(size=15), np.eye(15))
    pose_ids = sorted([joined.frame_id, *joined.ids[joined.kinds == 0].tolist()])
    stamps = {pose_ids[2]: 1_700_000_000_123_456_789, pose_ids[-1]: 5_000_000_001}
    msg = path_msg(joined, "map", STAMP, stamps)
    got = [(p.header.stamp.sec, p.header.stamp.nanosec) for p in msg.poses]
    assert got[2] == (1_700_000_000, 123_456_789) and got[-1] == (5, 1)  # to the nanosecond
    assert all(g == (12, 345) for k, g in enumerate(got) if k not in (2, len(got) - 1))  # others: the path's stamp
    assert all(p.header.frame_id == "map" for p in msg.poses)
    assert [(p.header.stamp.sec, p.header.stamp.nanosec) for p in path_msg(joined, "map", STAMP).poses] == [(12, 345)] * len(got)
    views = map_views(joined, 0, "map", STAMP, 0, stamps)
    assert [(p.header.stamp.sec, p.header.stamp.nanosec) for p in views.path.poses] == got
