"""Geometry: inverses against forward maps, exact Jacobians against finite differences."""

from __future__ import annotations

import numpy as np
import pytest

from linear_slam_ros.core import geometry as g
from support import inverse_pose


def _fd(fun, x: np.ndarray, eps: float = 1e-6) -> np.ndarray:
    cols = []
    for k in range(x.size):
        dx = np.zeros_like(x)
        dx[k] = eps
        cols.append((fun(x + dx) - fun(x - dx)) / (2 * eps))
    return np.stack(cols, -1)


def _random_pose(dim: int, rng: np.random.Generator) -> np.ndarray:
    t = rng.normal(size=dim) * 3
    if dim == 2:
        return np.concatenate([t, rng.uniform(-np.pi, np.pi, 1)])
    return np.concatenate([t, rng.uniform(-np.pi, np.pi, 1), rng.uniform(-1.2, 1.2, 1), rng.uniform(-np.pi, np.pi, 1)])


def test_wrap_angle_range_and_edges():
    a = np.array([np.pi, -np.pi, 3 * np.pi, -3 * np.pi + 1e-9, 0.0, 7.0])
    w = g.wrap_angle(a)
    assert np.all(w > -np.pi) and np.all(w <= np.pi)
    assert w[0] == np.pi and w[1] == np.pi and w[2] == pytest.approx(np.pi)
    np.testing.assert_allclose(np.cos(w), np.cos(a), atol=1e-12)


def test_rot3_matches_readme_convention(rng):
    a, b, c = 0.3, -0.4, 1.1
    rz = np.array([[np.cos(a), np.sin(a), 0], [-np.sin(a), np.cos(a), 0], [0, 0, 1]])
    ry = np.array([[np.cos(b), 0, -np.sin(b)], [0, 1, 0], [np.sin(b), 0, np.cos(b)]])
    rx = np.array([[1, 0, 0], [0, np.cos(c), np.sin(c)], [0, -np.sin(c), np.cos(c)]])
    np.testing.assert_allclose(g.rot3(np.array([a, b, c])), rx @ ry @ rz, atol=1e-15)
    np.testing.assert_allclose(g.angles3(rx @ ry @ rz), [a, b, c], atol=1e-14)


def test_angles3_inverts_rot3(rng):
    ang = np.stack([rng.uniform(-np.pi, np.pi, 50), rng.uniform(-1.5, 1.5, 50), rng.uniform(-np.pi, np.pi, 50)], -1)
    np.testing.assert_allclose(g.angles3(g.rot3(ang)), ang, atol=1e-12)


@pytest.mark.parametrize("dim", [2, 3])
def test_single_rotation_equals_batched(dim, rng):
    ang = _random_pose(dim, rng)[dim:]
    rot, drot = g.single_rotation(dim, ang)
    np.testing.assert_allclose(rot, g.rotation(dim, ang), atol=1e-15)
    np.testing.assert_allclose(drot, g.drotation(dim, ang), atol=1e-15)


def test_drot3_against_finite_differences(rng):
    ang = _random_pose(3, rng)[3:]
    np.testing.assert_allclose(g.drot3(ang), np.moveaxis(_fd(g.rot3, ang), -1, 0), atol=1e-8)


def test_dangles3_against_finite_differences(rng):
    ang = _random_pose(3, rng)[3:]
    rot = g.rot3(ang)
    directions = rng.normal(size=(4, 3, 3))
    analytic = g.dangles3(rot, directions)
    for k in range(4):
        numeric = (g.angles3(rot + 1e-7 * directions[k]) - g.angles3(rot - 1e-7 * directions[k])) / 2e-7
        np.testing.assert_allclose(analytic[:, k], numeric, atol=1e-6)


@pytest.mark.parametrize("dim", [2, 3])
def test_points_to_frame_jacobians(dim, rng):
    frame = _random_pose(dim, rng)
    point = rng.normal(size=dim) * 4
    res = g.points_to_frame(dim, frame[:dim], frame[dim:], point)
    np.testing.assert_allclose(
        res.d_point, _fd(lambda p: g.points_to_frame(dim, frame[:dim], frame[dim:], p).points, point), atol=1e-7
    )
    np.testing.assert_allclose(
        res.d_frame, _fd(lambda f: g.points_to_frame(dim, f[:dim], f[dim:], point).points, frame), atol=1e-7
    )


@pytest.mark.parametrize("dim", [2, 3])
def test_poses_to_frame_jacobians(dim, rng):
    frame, pose = _random_pose(dim, rng), _random_pose(dim, rng)

    def fwd(f, q):
        r = g.poses_to_frame(dim, f[:dim], f[dim:], q[:dim], q[dim:])
        return np.concatenate([r.translations, r.angles])

    res = g.poses_to_frame(dim, frame[:dim], frame[dim:], pose[:dim], pose[dim:])
    np.testing.assert_allclose(res.d_pose, _fd(lambda q: fwd(frame, q), pose), atol=1e-6)
    np.testing.assert_allclose(res.d_frame, _fd(lambda f: fwd(f, pose), frame), atol=1e-6)


@pytest.mark.parametrize("dim", [2, 3])
def test_inverse_pose_jacobian_and_identity(dim, rng):
    frame = _random_pose(dim, rng)
    inv = inverse_pose(dim, frame[:dim], frame[dim:])
    numeric = _fd(lambda f: np.concatenate(inverse_pose(dim, f[:dim], f[dim:])[:2]), frame)
    np.testing.assert_allclose(inv.d_frame, numeric, atol=1e-6)
    # the inverse composed with the pose gives the identity
    back = g.compose_relative(dim, frame, np.concatenate([inv.translation, inv.angles]))
    np.testing.assert_allclose(back, np.zeros(g.pose_size(dim)), atol=1e-12)


@pytest.mark.parametrize("dim", [2, 3])
def test_from_frame_inverts_to_frame(dim, rng):
    frame = _random_pose(dim, rng)
    pts = rng.normal(size=(10, dim))
    local = g.points_to_frame(dim, frame[:dim], frame[dim:], pts).points
    np.testing.assert_allclose(g.points_from_frame(dim, frame[:dim], frame[dim:], local), pts, atol=1e-12)
    pose = _random_pose(dim, rng)
    rel = g.relative_pose(dim, frame, pose)
    np.testing.assert_allclose(g.compose_relative(dim, frame, rel), pose, atol=1e-12)



def test_angles3_at_the_pitch_lock_still_gives_the_rotation(rng):
    """At pitch +-pi/2 only gamma -+ alpha is defined; a matrix made by products has its four lock
    entries as independent rounding noise, and the general formulas then read alpha and gamma from
    that noise (the rotation came back wrong by up to 2.0 before)."""
    for sign in (1.0, -1.0):
        for off in (0.0, 1e-15, 1e-12, 1e-9):
            for _ in range(50):
                ang = np.array([rng.uniform(-np.pi, np.pi), sign * (np.pi / 2 - off), rng.uniform(-np.pi, np.pi)])
                other = g.rot3(np.array([rng.uniform(-np.pi, np.pi), rng.uniform(-1.2, 1.2), rng.uniform(-np.pi, np.pi)]))
                product = (g.rot3(ang) @ other) @ other.T
                back = g.angles3(product)
                assert abs(back[1] - ang[1]) < 1e-7
                np.testing.assert_allclose(g.rot3(back), g.rot3(ang), rtol=0, atol=max(4 * off, 1e-14))


def test_dangles3_refuses_the_pitch_lock():
    near = g.rot3(np.array([0.4, np.pi / 2 - 1e-5, -0.2]))
    assert np.isfinite(g.dangles3(near, np.ones((1, 3, 3)))).all()  # 1e-5 rad from the lock: fine
    at = g.rot3(np.array([[0.4, 0.1, -0.2], [0.4, -np.pi / 2, -0.2]]))
    with pytest.raises(g.GeometryError, match=r"pitch at \+-90 deg \(\|cos beta\| = 6.12323e-17, below 1e-06\)"):
        g.dangles3(at, np.ones((2, 1, 3, 3)))
    assert g.pitch_lock_index(np.array([[0.0, 0.3, 0.0], [0.0, np.pi / 2, 0.0]])) == 1
    assert g.pitch_lock_index(np.array([[0.0, np.pi / 2 - 2e-6, 0.0]])) is None
