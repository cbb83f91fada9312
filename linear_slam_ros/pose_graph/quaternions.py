"""Orientations of the datasets' convention as unit quaternions (g2o's SE3 lines, TUM files).

A pose ``x y phi`` (2D) or ``x y z alpha beta gamma`` (3D) of the datasets maps points of the
pose's frame into its parent frame by ``p = R^T q + t``, with ``R`` =
:func:`linear_slam_ros.core.geometry.rotation` (``RX(gamma) RY(beta) RZ(alpha)``, a passive
matrix). The pose's orientation, as g2o, TUM and ROS state it (the *active* rotation, frame to
parent), is ``R^T``: a rotation by ``phi`` about z in 2D, yaw ``alpha``, pitch ``beta`` and
roll ``gamma`` (intrinsic z-y-x) in 3D. Quaternions are ``qx qy qz qw`` (Hamilton, scalar
last), unit norm, with ``qw >= 0``.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt
from scipy.spatial.transform import Rotation

from linear_slam_ros.core.geometry import angles3, rot3, wrap_angle

FloatArray = npt.NDArray[np.float64]


def _canonical(quats: FloatArray) -> FloatArray:
    """Return unit quaternions ``(..., 4)`` with ``qw >= 0`` (the sign g2o writes)."""
    q = quats / np.linalg.norm(quats, axis=-1, keepdims=True)
    return np.where(q[..., 3:] < 0.0, -q, q)


def angles_to_quaternions(dim: int, angles: npt.ArrayLike) -> FloatArray:
    """Return the orientation quaternions of poses' angles.

    Args:
        dim: 2 or 3.
        angles: ``(n, 1)`` (2D, ``phi``) or ``(n, 3)`` (3D, ``alpha beta gamma``) in radians.

    Returns:
        ``(n, 4)`` unit quaternions ``qx qy qz qw`` with ``qw >= 0``; in 2D ``(0, 0, sin(phi/2),
        cos(phi/2))`` up to sign.
    """
    a = np.asarray(angles, dtype=np.float64)
    if dim == 2:
        half = 0.5 * a.reshape(-1)
        zeros = np.zeros_like(half)
        return _canonical(np.stack([zeros, zeros, np.sin(half), np.cos(half)], -1))
    active = np.swapaxes(rot3(a.reshape(-1, 3)), -1, -2)
    return _canonical(np.asarray(Rotation.from_matrix(active).as_quat(), dtype=np.float64))


def quaternions_to_angles(dim: int, quats: npt.ArrayLike) -> FloatArray:
    """Return the poses' angles of orientation quaternions (inverse of :func:`angles_to_quaternions`).

    Args:
        dim: 2 or 3.
        quats: ``(n, 4)`` quaternions ``qx qy qz qw`` (normalised here; any sign).

    Returns:
        ``(n, 1)`` yaw in ``(-pi, pi]`` (2D: the heading of the body's x axis in the plane,
        ``atan2(R10, R00)`` of the active rotation, which is the rotation about z when there is
        no tilt; the tilt is dropped) or
        ``(n, 3)`` ``alpha beta gamma`` (3D, ranges of :func:`linear_slam_ros.core.geometry.angles3`).
    """
    q = _canonical(np.asarray(quats, dtype=np.float64).reshape(-1, 4))
    if dim == 2:
        x, y, z, w = q.T
        yaw = np.arctan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))
        return np.asarray(wrap_angle(yaw), dtype=np.float64).reshape(-1, 1)
    active = Rotation.from_quat(q).as_matrix()
    return np.asarray(angles3(np.swapaxes(active, -1, -2)), dtype=np.float64)
