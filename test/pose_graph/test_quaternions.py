"""Orientation quaternions to and from the poses' angles: round trips and known answers."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from linear_slam_ros.core.geometry import rot3
from linear_slam_ros.pose_graph.quaternions import angles_to_quaternions, quaternions_to_angles


def test_round_trips_in_2d_and_3d(rng):
    yaw = rng.uniform(-np.pi, np.pi, (50, 1))
    np.testing.assert_allclose(quaternions_to_angles(2, angles_to_quaternions(2, yaw)), yaw, atol=1e-14)
    ang = np.stack([rng.uniform(-np.pi, np.pi, 50), rng.uniform(-1.5, 1.5, 50), rng.uniform(-np.pi, np.pi, 50)], -1)
    back = quaternions_to_angles(3, angles_to_quaternions(3, ang))
    np.testing.assert_allclose(rot3(back), rot3(ang), atol=1e-14)


def test_2d_yaw_of_a_tilted_orientation_is_its_heading(rng):
    """A tilted base (roll and pitch of a few degrees, as a ROS odometry quaternion has) keeps its heading
    (ZYX Euler yaw); 2 atan2(qz, qw) read 56.44 deg for a yaw of 60 deg at 20 deg roll and pitch."""
    euler = np.array([[60.0, 20.0, 20.0], [170.0, 10.0, 10.0], [-179.0, -5.0, 3.0]])  # yaw, pitch, roll (deg)
    quats = Rotation.from_euler("ZYX", euler, degrees=True).as_quat()
    np.testing.assert_allclose(np.degrees(quaternions_to_angles(2, quats)[:, 0]), euler[:, 0], atol=1e-12)
    np.testing.assert_allclose(quaternions_to_angles(2, -quats), quaternions_to_angles(2, quats), atol=1e-15)  # either sign
    tilted = Rotation.from_euler("ZYX", np.c_[rng.uniform(-180, 180, 200), rng.uniform(-60, 60, (200, 2))], degrees=True)
    expected = tilted.as_euler("ZYX")[:, 0]
    got = quaternions_to_angles(2, tilted.as_quat())[:, 0]
    np.testing.assert_allclose(np.angle(np.exp(1j * (got - expected))), 0.0, atol=1e-12)
