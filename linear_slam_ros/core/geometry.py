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

from linear_slam_ros.core.errors import GeometryError

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


# Entries of RZ(a), dRZ, RY(b), dRY, RX(g), dRX (row-major, 9 each) as linear combinations of
# (1, cos a, sin a, cos b, sin b, cos g, sin g): one small product builds all six for a batch of
# poses, with the same values as the elementary matrices above (coefficients 0 and +-1 are exact).
_ELEMENTARY = np.zeros((7, 6, 9))
for _m, _entries in enumerate(
    (
        ((0, 1, 1), (1, 2, 1), (3, 2, -1), (4, 1, 1), (8, 0, 1)),  # RZ
        ((0, 2, -1), (1, 1, 1), (3, 1, -1), (4, 2, -1)),  # dRZ
        ((0, 3, 1), (2, 4, -1), (4, 0, 1), (6, 4, 1), (8, 3, 1)),  # RY
        ((0, 4, -1), (2, 3, -1), (6, 3, 1), (8, 4, -1)),  # dRY
        ((0, 0, 1), (4, 5, 1), (5, 6, 1), (7, 6, -1), (8, 5, 1)),  # RX
        ((4, 6, -1), (5, 5, 1), (7, 5, -1), (8, 6, -1)),  # dRX
    )
):
    for _entry, _src, _sign in _entries:
        _ELEMENTARY[_src, _m, _entry] = _sign
_ELEMENTARY_FLAT = _ELEMENTARY.reshape(7, 54)


def _elementary3(angles: FloatArray) -> FloatArray:
    """Return ``RZ, dRZ, RY, dRY, RX, dRX`` of ``(..., 3)`` angles, shape ``(..., 6, 3, 3)``."""
    basis = np.empty(angles.shape[:-1] + (7,))
    basis[..., 0] = 1.0
    basis[..., 1::2] = np.cos(angles)
    basis[..., 2::2] = np.sin(angles)
    return (basis @ _ELEMENTARY_FLAT).reshape(angles.shape[:-1] + (6, 3, 3))


def rot3(angles: FloatArray) -> FloatArray:
    """Return ``R = RX(gamma) RY(beta) RZ(alpha)``, shape ``(..., 3, 3)``, from ``(..., 3)`` angles."""
    e = _elementary3(angles)
    return e[..., 4, :, :] @ e[..., 2, :, :] @ e[..., 0, :, :]


def drot3(angles: FloatArray) -> FloatArray:
    """Return ``dR/d(alpha, beta, gamma)``, shape ``(..., 3, 3, 3)``: index ``[..., k, :, :]``."""
    return rot3_and_drot3(angles)[1]


def rot3_and_drot3(angles: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Return :func:`rot3` and :func:`drot3` of ``(..., 3)`` angles together (one set of sines and cosines)."""
    e = _elementary3(angles)
    rz, drz, ry, dry, rx, drx = (e[..., i, :, :] for i in range(6))
    rxy = rx @ ry
    out = np.empty(angles.shape[:-1] + (3, 3, 3))
    np.matmul(rxy, drz, out=out[..., 0, :, :])
    np.matmul(rx @ dry, rz, out=out[..., 1, :, :])
    np.matmul(drx @ ry, rz, out=out[..., 2, :, :])
    return rxy @ rz, out


def angles3(rot: FloatArray) -> FloatArray:
    """Return ``(alpha, beta, gamma)``, shape ``(..., 3)``, of rotation matrices ``(..., 3, 3)``.

    ``beta`` lies in ``[-pi/2, pi/2]``; ``alpha`` and ``gamma`` in ``(-pi, pi]``. At pitch +-pi/2
    (gimbal lock: ``cos beta`` below ``sqrt(eps)``, where the general formulas' ``alpha`` and
    ``gamma`` are rounding noise) only ``gamma -+ alpha`` is defined: ``alpha`` is 0 and ``gamma``
    takes all of it, so the triple still gives ``rot`` (to ``cos beta``).
    """
    h = np.hypot(rot[..., 0, 0], rot[..., 0, 1])
    alpha = np.arctan2(rot[..., 0, 1], rot[..., 0, 0])
    beta = np.arctan2(-rot[..., 0, 2], h)
    gamma = np.arctan2(rot[..., 1, 2], rot[..., 2, 2])
    locked = h < _SQRT_EPS
    if np.any(locked):
        alpha = np.where(locked, 0.0, alpha)
        gamma = np.where(locked, np.arctan2(np.copysign(1.0, -rot[..., 0, 2]) * rot[..., 1, 0], rot[..., 1, 1]), gamma)
    return np.stack([alpha, beta, gamma], -1)


_SQRT_EPS = math.sqrt(np.finfo(np.float64).eps)


def dangles3(rot: FloatArray, drot: FloatArray) -> FloatArray:
    """Return the derivative of :func:`angles3` at ``rot`` along ``drot``.

    The derivative is linear in the five entries of ``drot`` that :func:`angles3` reads; its
    ``(3, 5)`` matrix depends on ``rot`` only, so it is built once per matrix and applied to all
    ``k`` directions in one product.

    Args:
        rot: rotation matrices, ``(..., 3, 3)``.
        drot: directions, ``(..., k, 3, 3)`` (``k`` directions per matrix).

    Returns:
        ``(..., 3, k)``: column ``j`` is ``d(alpha, beta, gamma)`` along ``drot[..., j, :, :]``.

    Raises:
        GeometryError: a rotation's pitch is at +-pi/2 (``|cos beta| <`` :data:`PITCH_LOCK_COS`),
            where the derivative is singular.
    """
    batch = rot.shape[:-2]
    m = np.reshape(rot, batch + (9,))[..., _ANGLE_ENTRIES]  # m00 m01 m02 m12 m22
    m00, m01, m02, m12, m22 = (m[..., i] for i in range(5))
    h2 = m00 * m00 + m01 * m01
    h = np.sqrt(h2)
    if h.size and not np.min(h) >= PITCH_LOCK_COS:
        raise GeometryError(pitch_lock_message("a rotation of a change of frame", float(np.min(h))))
    beta_scale = 1.0 / (h2 + m02 * m02)
    cross = m02 * beta_scale / h
    gamma_scale = 1.0 / (m12 * m12 + m22 * m22)
    jac = np.zeros(batch + (3, 5))
    jac[..., 0, 0] = -m01 / h2
    jac[..., 0, 1] = m00 / h2
    jac[..., 1, 0] = m00 * cross
    jac[..., 1, 1] = m01 * cross
    jac[..., 1, 2] = -h * beta_scale
    jac[..., 2, 3] = m22 * gamma_scale
    jac[..., 2, 4] = -m12 * gamma_scale
    d = np.reshape(drot, drot.shape[:-2] + (9,))[..., _ANGLE_ENTRIES]  # (..., k, 5)
    return jac @ np.swapaxes(d, -1, -2)


PITCH_LOCK_COS = 1e-6
"""Smallest ``|cos beta|`` of a 3D orientation the joins accept (``beta`` the pitch; pitch within about
1e-6 rad of +-pi/2 is refused). At ``beta = +-pi/2`` the Euler angles (the paper's parameterisation) lose a
degree of freedom: only ``alpha -+ gamma`` is defined, :func:`dangles3` divides by ``cos^2 beta`` and
a change of frame would give information of 1e32 and a wrong rotation. At ``|cos beta| = 1e-6`` the
joins are still exact to 1e-10; a rotation's angles read from its matrix lose ``1e-16 / |cos beta|``
rad."""


def pitch_lock_index(angles: FloatArray) -> int | None:
    """Return the first row of ``(m, 3)`` Euler angles ``(alpha, beta, gamma)`` whose pitch is at the lock
    (``|cos beta| < PITCH_LOCK_COS``), or None."""
    bad = np.flatnonzero(~(np.abs(np.cos(angles[:, 1])) >= PITCH_LOCK_COS))
    return int(bad[0]) if bad.size else None


def pitch_lock_message(what: str, cos_beta: float) -> str:
    """Return why ``what``'s orientation cannot be joined: its pitch is at the Euler angles' singularity."""
    return (
        f"{what} has pitch at +-90 deg (|cos beta| = {cos_beta:.6g}, below {PITCH_LOCK_COS:g}): Euler angles are "
        "singular there (gimbal lock), so it cannot be joined; express the map in the frame of a pose that is not "
        "pitched by 90 deg from it"
    )


def canonical_angles3(angles: FloatArray) -> tuple[FloatArray, npt.NDArray[np.bool_]]:
    """Return ``(m, 3)`` Euler angles with every pitch within ``[-pi/2, pi/2]``, and which rows changed.

    A triple whose wrapped pitch is beyond ``pi/2`` in magnitude is replaced by the other triple of
    the same rotation, ``(alpha + pi, pi - beta, gamma + pi)`` (wrapped), which :func:`angles3`
    gives; the others are returned as they are. The map is affine with Jacobian
    ``diag(1, -1, 1)``, so information over a changed triple is carried exactly by negating its
    ``beta`` row and column. The linear joins wrap angle differences by ``2 pi`` one angle at a
    time (Remark 3): the other triple of a rotation differs from the canonical one by ``pi`` in
    each angle, and two maps giving one rotation by different triples were averaged into a wrong one.
    """
    angles = np.asarray(angles, dtype=np.float64)
    flip = np.abs(wrap_angle(angles[:, 1])) > math.pi / 2
    if not flip.any():
        return angles, flip
    out = angles.copy()
    out[flip] = wrap_angle(np.stack([angles[flip, 0] + math.pi, math.pi - angles[flip, 1], angles[flip, 2] + math.pi], -1))
    return out, flip


_ANGLE_ENTRIES = np.array([0, 1, 2, 5, 8])
"""Flat indices of the entries of a rotation that :func:`angles3` reads: 00, 01, 02, 12, 22."""


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
    # RX(g) RY(b) RZ(a) and its three derivatives, multiplied out.
    sgsb, cgsb, sgcb, cgcb = sg * sb, cg * sb, sg * cb, cg * cb
    rot = np.array(
        [
            [cb * ca, cb * sa, -sb],
            [sgsb * ca - cg * sa, sgsb * sa + cg * ca, sgcb],
            [cgsb * ca + sg * sa, cgsb * sa - sg * ca, cgcb],
        ]
    )
    drot = np.array(
        [
            [
                [-cb * sa, cb * ca, 0.0],
                [-sgsb * sa - cg * ca, sgsb * ca - cg * sa, 0.0],
                [-cgsb * sa + sg * ca, cgsb * ca + sg * sa, 0.0],
            ],
            [[-sb * ca, -sb * sa, -cb], [sgcb * ca, sgcb * sa, -sgsb], [cgcb * ca, cgcb * sa, -cgsb]],
            [[0.0, 0.0, 0.0], rot[2], -rot[1]],
        ]
    )
    return rot, drot


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
