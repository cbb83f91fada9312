"""2D and 3D coordinate transforms in the benchmark datasets' conventions, with exact Jacobians.

Conventions (``shared/datasets/README.md``, verified on the data by the golden χ² tests):

* A 2D pose is ``(x, y, phi)``; a 3D pose is ``(x, y, z, alpha, beta, gamma)``.
* ``R(phi) = [[cos, sin], [-sin, cos]]`` in 2D and ``R = RX(gamma) RY(beta) RZ(alpha)`` in 3D,
  with the README's elementary matrices. ``R`` maps world directions into the pose frame:
  a world point ``X`` has coordinates ``R (X - t)`` in the frame of pose ``(t, R)``.
* The orientation of pose ``j`` seen from pose ``r`` is ``R_j R_r^T``.

Every function is vectorised over leading batch dimensions: translations are ``(..., d)``,
angles ``(..., a)`` with ``d`` the dimension and ``a = 1`` (2D) or ``3`` (3D). Jacobians are
returned as ``(..., rows, cols)`` arrays. Units: metres and radians.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]

TWO_PI = 2.0 * np.pi


def point_size(dim: int) -> int:
    """Return the number of scalars of a point feature in ``dim`` dimensions."""
    return dim


def angle_size(dim: int) -> int:
    """Return the number of orientation scalars of a pose in ``dim`` dimensions."""
    return 1 if dim == 2 else 3


def pose_size(dim: int) -> int:
    """Return the number of scalars of a pose in ``dim`` dimensions (3 or 6)."""
    return dim + angle_size(dim)


def wrap_angle(angle: npt.ArrayLike) -> FloatArray:
    """Wrap angles (rad) into ``(-pi, pi]``, elementwise."""
    a = np.asarray(angle, dtype=np.float64)
    # pi - ((pi - a) mod 2 pi) lies in (-pi, pi]: +pi stays +pi, -pi maps to +pi.
    return np.pi - np.mod(np.pi - a, TWO_PI)


# --------------------------------------------------------------------------- rotations


def rot2(phi: FloatArray) -> FloatArray:
    """Return ``R(phi)``, shape ``(..., 2, 2)``, for angles ``phi`` of shape ``(...)``."""
    c, s = np.cos(phi), np.sin(phi)
    return np.stack([np.stack([c, s], -1), np.stack([-s, c], -1)], -2)


def drot2(phi: FloatArray) -> FloatArray:
    """Return ``dR/dphi``, shape ``(..., 2, 2)``."""
    c, s = np.cos(phi), np.sin(phi)
    return np.stack([np.stack([-s, c], -1), np.stack([-c, -s], -1)], -2)


def _rz(a: FloatArray) -> FloatArray:
    c, s, z, o = np.cos(a), np.sin(a), np.zeros_like(a), np.ones_like(a)
    return np.stack([np.stack([c, s, z], -1), np.stack([-s, c, z], -1), np.stack([z, z, o], -1)], -2)


def _drz(a: FloatArray) -> FloatArray:
    c, s, z = np.cos(a), np.sin(a), np.zeros_like(a)
    return np.stack([np.stack([-s, c, z], -1), np.stack([-c, -s, z], -1), np.stack([z, z, z], -1)], -2)


def _ry(b: FloatArray) -> FloatArray:
    c, s, z, o = np.cos(b), np.sin(b), np.zeros_like(b), np.ones_like(b)
    return np.stack([np.stack([c, z, -s], -1), np.stack([z, o, z], -1), np.stack([s, z, c], -1)], -2)


def _dry(b: FloatArray) -> FloatArray:
    c, s, z = np.cos(b), np.sin(b), np.zeros_like(b)
    return np.stack([np.stack([-s, z, -c], -1), np.stack([z, z, z], -1), np.stack([c, z, -s], -1)], -2)


def _rx(g: FloatArray) -> FloatArray:
    c, s, z, o = np.cos(g), np.sin(g), np.zeros_like(g), np.ones_like(g)
    return np.stack([np.stack([o, z, z], -1), np.stack([z, c, s], -1), np.stack([z, -s, c], -1)], -2)


def _drx(g: FloatArray) -> FloatArray:
    c, s, z = np.cos(g), np.sin(g), np.zeros_like(g)
    return np.stack([np.stack([z, z, z], -1), np.stack([z, -s, c], -1), np.stack([z, -c, -s], -1)], -2)


def rot3(angles: FloatArray) -> FloatArray:
    """Return ``R = RX(gamma) RY(beta) RZ(alpha)``, shape ``(..., 3, 3)``, from ``(..., 3)`` angles."""
    a, b, g = angles[..., 0], angles[..., 1], angles[..., 2]
    return _rx(g) @ _ry(b) @ _rz(a)


def drot3(angles: FloatArray) -> FloatArray:
    """Return ``dR/d(alpha, beta, gamma)``, shape ``(..., 3, 3, 3)``: index ``[..., k, :, :]``."""
    a, b, g = angles[..., 0], angles[..., 1], angles[..., 2]
    rx, ry, rz = _rx(g), _ry(b), _rz(a)
    return np.stack([rx @ ry @ _drz(a), rx @ _dry(b) @ rz, _drx(g) @ ry @ rz], -3)


def angles3(rot: FloatArray) -> FloatArray:
    """Return ``(alpha, beta, gamma)``, shape ``(..., 3)``, of rotation matrices ``(..., 3, 3)``.

    ``beta`` lies in ``[-pi/2, pi/2]``; ``alpha`` and ``gamma`` in ``(-pi, pi]``.
    """
    alpha = np.arctan2(rot[..., 0, 1], rot[..., 0, 0])
    beta = np.arctan2(-rot[..., 0, 2], np.hypot(rot[..., 0, 0], rot[..., 0, 1]))
    gamma = np.arctan2(rot[..., 1, 2], rot[..., 2, 2])
    return np.stack([alpha, beta, gamma], -1)


def dangles3(rot: FloatArray, drot: FloatArray) -> FloatArray:
    """Return the derivative of :func:`angles3` at ``rot`` along ``drot``.

    Args:
        rot: rotation matrices, ``(..., 3, 3)``.
        drot: directions, ``(..., k, 3, 3)`` (``k`` directions per matrix).

    Returns:
        ``(..., 3, k)``: column ``j`` is ``d(alpha, beta, gamma)`` along ``drot[..., j, :, :]``.
    """
    m = rot[..., None, :, :]
    m00, m01, m02, m12, m22 = m[..., 0, 0], m[..., 0, 1], m[..., 0, 2], m[..., 1, 2], m[..., 2, 2]
    d00, d01, d02 = drot[..., 0, 0], drot[..., 0, 1], drot[..., 0, 2]
    d12, d22 = drot[..., 1, 2], drot[..., 2, 2]
    h2 = m00 * m00 + m01 * m01
    h = np.sqrt(h2)
    dalpha = (m00 * d01 - m01 * d00) / h2
    dh = (m00 * d00 + m01 * d01) / h
    dbeta = (-h * d02 + m02 * dh) / (h2 + m02 * m02)
    dgamma = (m22 * d12 - m12 * d22) / (m12 * m12 + m22 * m22)
    return np.stack([dalpha, dbeta, dgamma], -2)


def rotation(dim: int, angles: FloatArray) -> FloatArray:
    """Return rotation matrices ``(..., d, d)`` from pose angles ``(..., a)``."""
    return rot2(angles[..., 0]) if dim == 2 else rot3(angles)


def drotation(dim: int, angles: FloatArray) -> FloatArray:
    """Return ``dR/dangles``, shape ``(..., a, d, d)``."""
    return drot2(angles[..., 0])[..., None, :, :] if dim == 2 else drot3(angles)


def single_rotation(dim: int, angles: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Return ``(R, dR/dangles)`` of ONE pose, shapes ``(d, d)`` and ``(a, d, d)``.

    Same values as :func:`rotation` and :func:`drotation` for unbatched angles, computed with
    scalar math: the change of frame of a whole map needs only its frame pose's rotation.
    """
    if dim == 2:
        c, s = math.cos(angles[0]), math.sin(angles[0])
        return np.array([[c, s], [-s, c]]), np.array([[[-s, c], [-c, -s]]])
    ca, sa = math.cos(angles[0]), math.sin(angles[0])
    cb, sb = math.cos(angles[1]), math.sin(angles[1])
    cg, sg = math.cos(angles[2]), math.sin(angles[2])
    rz = np.array([[ca, sa, 0.0], [-sa, ca, 0.0], [0.0, 0.0, 1.0]])
    drz = np.array([[-sa, ca, 0.0], [-ca, -sa, 0.0], [0.0, 0.0, 0.0]])
    ry = np.array([[cb, 0.0, -sb], [0.0, 1.0, 0.0], [sb, 0.0, cb]])
    dry = np.array([[-sb, 0.0, -cb], [0.0, 0.0, 0.0], [cb, 0.0, -sb]])
    rx = np.array([[1.0, 0.0, 0.0], [0.0, cg, sg], [0.0, -sg, cg]])
    drx = np.array([[0.0, 0.0, 0.0], [0.0, -sg, cg], [0.0, -cg, -sg]])
    rxy = rx @ ry
    return rxy @ rz, np.stack([rxy @ drz, rx @ dry @ rz, drx @ ry @ rz])


# ------------------------------------------------------------------- frame operations


class PointsInFrame(NamedTuple):
    """Points expressed in a pose frame, with Jacobians.

    Attributes:
        points: ``(..., d)`` coordinates in the frame of ``T``.
        d_point: ``(..., d, d)`` Jacobian with respect to the world point.
        d_frame: ``(..., d, d + a)`` Jacobian with respect to the frame pose ``T``.
    """

    points: FloatArray
    d_point: FloatArray
    d_frame: FloatArray


class PosesInFrame(NamedTuple):
    """Poses expressed in a pose frame, with Jacobians.

    Attributes:
        translations: ``(..., d)``.
        angles: ``(..., a)``, wrapped.
        d_pose: ``(..., d + a, d + a)`` Jacobian with respect to the world pose.
        d_frame: ``(..., d + a, d + a)`` Jacobian with respect to the frame pose ``T``.
    """

    translations: FloatArray
    angles: FloatArray
    d_pose: FloatArray
    d_frame: FloatArray





def points_to_frame(dim: int, t_frame: FloatArray, ang_frame: FloatArray, points: FloatArray) -> PointsInFrame:
    """Express world ``points`` in the frame of pose ``(t_frame, ang_frame)``: ``R (p - t)``.

    Args:
        dim: 2 or 3.
        t_frame: ``(..., d)`` frame translation (m), broadcast against ``points``.
        ang_frame: ``(..., a)`` frame angles (rad).
        points: ``(..., d)`` world points (m).
    """
    rot = rotation(dim, ang_frame)
    drot = drotation(dim, ang_frame)
    diff = points - t_frame
    local = np.einsum("...ij,...j->...i", rot, diff)
    shape = np.broadcast_shapes(rot.shape, local.shape[:-1] + (dim, dim))
    d_point = np.broadcast_to(rot, shape)
    d_ang = np.einsum("...kij,...j->...ik", drot, diff)
    d_frame = np.concatenate([-d_point, d_ang], -1)
    return PointsInFrame(local, d_point, d_frame)


def poses_to_frame(
    dim: int, t_frame: FloatArray, ang_frame: FloatArray, t_pose: FloatArray, ang_pose: FloatArray
) -> PosesInFrame:
    """Express world poses ``(t_pose, ang_pose)`` in the frame of pose ``(t_frame, ang_frame)``.

    The result is ``(R_T (t - t_T), angles(R R_T^T))``, angles wrapped into ``(-pi, pi]``.
    """
    d = dim
    pts = points_to_frame(dim, t_frame, ang_frame, t_pose)
    batch = pts.points.shape[:-1]
    p = pose_size(dim)
    d_pose = np.zeros(batch + (p, p))
    d_frame = np.zeros(batch + (p, p))
    d_pose[..., :d, :d] = pts.d_point
    d_frame[..., :d, :] = pts.d_frame
    if dim == 2:
        ang = wrap_angle(ang_pose - ang_frame)
        d_pose[..., 2, 2] = 1.0
        d_frame[..., 2, 2] = -1.0
    else:
        rot_t = rot3(ang_frame)
        rot_p = rot3(ang_pose)
        rel = rot_p @ np.swapaxes(rot_t, -1, -2)
        ang = angles3(rel)
        dir_pose = drot3(ang_pose) @ np.swapaxes(rot_t, -1, -2)[..., None, :, :]
        dir_frame = rot_p[..., None, :, :] @ np.swapaxes(drot3(ang_frame), -1, -2)
        d_pose[..., 3:, 3:] = dangles3(rel, dir_pose)
        d_frame[..., 3:, 3:] = dangles3(rel, dir_frame)
    return PosesInFrame(pts.points, ang, d_pose, d_frame)


def points_from_frame(dim: int, t_frame: FloatArray, ang_frame: FloatArray, local: FloatArray) -> FloatArray:
    """Return world points from coordinates ``local`` in the frame of ``T``: ``R^T p + t``."""
    rot = rotation(dim, ang_frame)
    return np.einsum("...ji,...j->...i", rot, local) + t_frame


def poses_from_frame(
    dim: int, t_frame: FloatArray, ang_frame: FloatArray, t_local: FloatArray, ang_local: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """Return world poses from poses given in the frame of ``T`` (inverse of :func:`poses_to_frame`)."""
    t_world = points_from_frame(dim, t_frame, ang_frame, t_local)
    if dim == 2:
        return t_world, wrap_angle(ang_local + ang_frame)
    return t_world, angles3(rot3(ang_local) @ rot3(ang_frame))


def compose_relative(dim: int, pose_a: FloatArray, pose_ab: FloatArray) -> FloatArray:
    """Return world pose ``b`` from world pose ``a`` and ``b`` seen from ``a`` (``(..., d + a)`` each)."""
    t, ang = poses_from_frame(dim, pose_a[..., :dim], pose_a[..., dim:], pose_ab[..., :dim], pose_ab[..., dim:])
    return np.concatenate([t, ang], -1)


def relative_pose(dim: int, pose_a: FloatArray, pose_b: FloatArray) -> FloatArray:
    """Return pose ``b`` seen from pose ``a`` (both world poses, ``(..., d + a)``)."""
    res = poses_to_frame(dim, pose_a[..., :dim], pose_a[..., dim:], pose_b[..., :dim], pose_b[..., dim:])
    return np.concatenate([res.translations, res.angles], -1)
