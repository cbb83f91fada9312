"""The TF output of ``publish_tf`` without DDS: one transform per child frame and stamp, and REP-105's
``map -> odom`` composed with the odometry (``odom_frame``)."""

from __future__ import annotations

import numpy as np
import pytest
from builtin_interfaces.msg import Time
from geometry_msgs.msg import Quaternion, Transform, TransformStamped, Vector3
from scipy.spatial.transform import Rotation
from std_msgs.msg import Header

from linear_slam_ros.ros.tf_output import TfOutput, map_to_odom
from msg_adapters.views import transform_msg


def _transform(parent: str, child: str, rotation: Rotation, translation, stamp: Time | None = None) -> TransformStamped:
    qx, qy, qz, qw = rotation.as_quat()
    return TransformStamped(
        header=Header(frame_id=parent, stamp=stamp or Time(sec=5)), child_frame_id=child,
        transform=Transform(translation=Vector3(x=translation[0], y=translation[1], z=translation[2]),
                            rotation=Quaternion(x=qx, y=qy, z=qz, w=qw)),
    )


def _matrix(t: TransformStamped) -> np.ndarray:
    q, p = t.transform.rotation, t.transform.translation
    out = np.eye(4)
    out[:3, :3] = Rotation.from_quat([q.x, q.y, q.z, q.w]).as_matrix()
    out[:3, 3] = [p.x, p.y, p.z]
    return out


def test_map_to_odom_composed_with_the_odometry_gives_the_map_pose(rng):
    """REP-105: the SLAM node sends map -> odom such that map -> odom -> base is its pose of base."""
    map_base = _transform("map", "base_link", Rotation.random(random_state=1), rng.normal(size=3))
    odom_base = _transform("odom", "base_link", Rotation.random(random_state=2), rng.normal(size=3))
    map_odom = map_to_odom(map_base, odom_base)
    assert (map_odom.header.frame_id, map_odom.child_frame_id) == ("map", "odom")
    assert (map_odom.header.stamp.sec, map_odom.header.stamp.nanosec) == (5, 0)
    np.testing.assert_allclose(_matrix(map_odom) @ _matrix(odom_base), _matrix(map_base), atol=1e-12)
    same = map_to_odom(map_base, _transform("odom", "base_link", Rotation.identity(), [0.0, 0.0, 0.0]))
    np.testing.assert_allclose(_matrix(same), _matrix(map_base), atol=1e-15)  # odometry at its origin


def test_one_transform_per_child_frame_and_stamp():
    """A second pose of an instant already sent (the global map's after the arrival's) is not sent: TF listeners
    take a repeated stamp as a publisher error or keep both (review of session 26)."""
    sent: list[TransformStamped] = []
    tf = TfOutput(sent.append)
    pose = np.array([1.0, 2.0, 0.3])
    assert tf.publish(transform_msg(2, pose, "map", "base_link", Time(sec=10)))
    assert not tf.publish(transform_msg(2, pose + 1.0, "map", "base_link", Time(sec=10)))  # the same stamp
    assert not tf.publish(transform_msg(2, pose, "map", "base_link", Time(sec=9, nanosec=999)))  # older
    assert tf.publish(transform_msg(2, pose, "map", "a/base_link", Time(sec=10)))  # another robot's frame
    assert tf.publish(transform_msg(2, pose, "map", "base_link", Time(sec=10, nanosec=1)))
    assert [t.child_frame_id for t in sent] == ["base_link", "a/base_link", "base_link"]
    assert (tf.n_sent, tf.n_repeated) == (3, 2)
    tf.reset()  # a new map (~/reset, ~/load_map) may start earlier
    assert tf.publish(transform_msg(2, pose, "map", "base_link", Time(sec=1)))


def test_with_odom_frame_the_transform_goes_to_odom_or_not_at_all():
    sent: list[TransformStamped] = []
    warnings: list[str] = []
    odometry = {(7, 0): _transform("odom", "base_link", Rotation.from_euler("z", 0.5), [1.0, 0.0, 0.0], Time(sec=7))}

    def lookup(odom_frame: str, base_frame: str, stamp: Time) -> TransformStamped:
        assert (odom_frame, base_frame) == ("odom", "base_link")
        try:
            return odometry[(stamp.sec, stamp.nanosec)]
        except KeyError:
            raise LookupError(f"no odometry at {stamp.sec} s") from None

    tf = TfOutput(sent.append, "odom", lookup, warnings.append)
    map_base = transform_msg(2, np.array([3.0, 4.0, 1.0]), "map", "base_link", Time(sec=7))
    assert tf.publish(map_base)
    assert (sent[0].header.frame_id, sent[0].child_frame_id) == ("map", "odom")
    np.testing.assert_allclose(_matrix(sent[0]) @ _matrix(odometry[(7, 0)]), _matrix(map_base), atol=1e-12)
    assert not tf.publish(transform_msg(2, np.zeros(3), "map", "base_link", Time(sec=8)))
    assert tf.n_no_odometry == 1 and len(sent) == 1
    assert warnings == ["no TF sent at 8.000000000: no odom -> base_link there (no odometry at 8 s)"]
    assert tf.publish(transform_msg(2, np.zeros(3), "map", "base_link", Time(sec=8))) is False  # still none: not sent
    odometry[(8, 0)] = odometry[(7, 0)]
    assert tf.publish(transform_msg(2, np.zeros(3), "map", "base_link", Time(sec=8)))  # a failed stamp may come again


def test_odom_frame_needs_a_lookup():
    with pytest.raises(ValueError, match="^odom_frame 'odom' needs an odometry lookup \\(tf2_ros\\)$"):
        TfOutput(print, "odom")


def test_map_to_odom_is_sent_again_ahead_of_the_clock_and_never_at_a_stamp_already_sent():
    """Between submaps only odometry moved: a lookup of map -> base at the current time extrapolated past the newest
    map -> odom and failed (tf2), which a navigation stack meets at once."""
    sent: list[TransformStamped] = []
    odom_base = _transform("odom", "base_link", Rotation.from_euler("z", 0.2), [0.5, 0.0, 0.0], Time(sec=7))
    tf = TfOutput(sent.append, "odom", lambda odom, base, stamp: odom_base)
    assert not tf.resend(Time(sec=7, nanosec=50))  # nothing sent yet: nothing to send again
    map_base = transform_msg(2, np.array([3.0, 4.0, 1.0]), "map", "base_link", Time(sec=7))
    assert tf.publish(map_base)
    assert tf.resend(Time(sec=7, nanosec=100_000_000))
    assert not tf.resend(Time(sec=7, nanosec=100_000_000))  # a stopped clock (sim time after a bag): no repeated stamp
    assert tf.resend(Time(sec=7, nanosec=150_000_000))
    assert [(t.header.stamp.sec, t.header.stamp.nanosec) for t in sent] == [(7, 0), (7, 100_000_000), (7, 150_000_000)]
    assert all((t.header.frame_id, t.child_frame_id) == ("map", "odom") for t in sent)
    for t in sent[1:]:
        np.testing.assert_array_equal(_matrix(t), _matrix(sent[0]))  # the same correction, later
    assert tf.n_resent == 2 and tf.n_sent == 1
    assert not tf.resend(Time(sec=7))  # never at a stamp a pose's map -> odom went out at
    assert tf.publish(transform_msg(2, np.zeros(3), "map", "base_link", Time(sec=7, nanosec=120_000_000)))  # a submap's
    assert tf.resend(Time(sec=7, nanosec=130_000_000), "world")  # under the node's current map_frame
    assert (sent[-1].header.frame_id, sent[-1].child_frame_id) == ("world", "odom")
    np.testing.assert_array_equal(_matrix(sent[-1]), _matrix(sent[-2]))  # the newest correction (the submap's)
    assert tf.resend(Time(sec=3))  # the clock went back (a bag played again): followed
    tf.reset()  # a new map: the old correction is not sent again
    assert not tf.resend(Time(sec=9))
    assert tf.publish(transform_msg(2, np.zeros(3), "map", "base_link", Time(sec=1)))  # the new map, earlier stamps
    assert tf.resend(Time(sec=1, nanosec=50_000_000)) and tf.resend(Time(sec=7, nanosec=100_000_000))  # stamps forgotten
    plain = TfOutput(sent.append)  # map -> base_link: sent again, it would say the robot stood still
    assert plain.publish(map_base) and not plain.resend(Time(sec=8))
