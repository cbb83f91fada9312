"""Synthetic worlds with ground truth, for known-answer tests and demos.

A world is a robot trajectory (pose 0 at the origin) and point features, in 2D or 3D. From it
come local maps of three kinds:

* :func:`exact_local_maps` and :func:`exact_pose_graph_maps`: noise-free maps, every estimate
  exactly the truth seen from the map's frame, with random SPD information;
* :func:`noisy_local_maps`: odometry and feature observations with Gaussian noise, each local
  map built by Gauss-Newton over its measurements in its start pose's frame, intermediate poses
  marginalised out (the benchmark datasets' shape).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from linear_slam_ros.core.geometry import (
    angle_size,
    compose_relative,
    points_from_frame,
    points_to_frame,
    pose_size,
    poses_to_frame,
    relative_pose,
    wrap_angle,
)
from linear_slam_ros.core.local_map import FEATURE, POSE, LocalMap
from linear_slam_ros.evaluation.nonlinear import gauss_newton

FloatArray = npt.NDArray[np.float64]


@dataclass(frozen=True)
class World:
    """Ground truth: poses ``(N + 1, p)`` in the frame of pose 0, features ``{id: (d,)}``."""

    dim: int
    poses: FloatArray
    features: dict[int, FloatArray]

    def truth(self) -> dict[tuple[int, int], FloatArray]:
        """Return ``{(kind, id): value}`` for every pose but 0 and every feature."""
        out: dict[tuple[int, int], FloatArray] = {(POSE, k): self.poses[k] for k in range(1, len(self.poses))}
        out.update({(FEATURE, f): p for f, p in self.features.items()})
        return out

    def visible(self, pose_index: int, sensor_range: float) -> list[int]:
        """Return ids of features within ``sensor_range`` of a pose (m)."""
        t = self.poses[pose_index, : self.dim]
        return [f for f, p in self.features.items() if np.linalg.norm(p - t) <= sensor_range]


def make_world(dim: int, n_poses: int, n_features: int, rng: np.random.Generator, loops: float = 1.0) -> World:
    """Return a world: a loop trajectory of ``n_poses + 1`` poses and features scattered around it.

    The robot drives ``loops`` times around a circle of radius 10 m (a gentle helix in 3D), so
    long runs revisit features and wrap orientations past ``pi``.
    """
    k = np.arange(n_poses + 1)
    theta = 2 * np.pi * loops * k / n_poses
    radius = 10.0
    p = pose_size(dim)
    poses = np.zeros((n_poses + 1, p))
    if dim == 2:
        poses[:, 0] = radius * np.sin(theta)
        poses[:, 1] = radius * (1 - np.cos(theta))
        poses[:, 2] = wrap_angle(theta)
    else:
        poses[:, 0] = radius * np.sin(theta)
        poses[:, 1] = radius * (1 - np.cos(theta))
        poses[:, 2] = 0.5 * np.sin(theta * 0.5)
        poses[:, 3] = wrap_angle(theta)
        poses[:, 4] = 0.05 * np.sin(3 * theta)
        poses[:, 5] = 0.05 * np.cos(2 * theta) - 0.05
    poses[0] = 0.0
    angle = rng.uniform(0, 2 * np.pi, n_features)
    dist = radius + rng.uniform(-4.0, 4.0, n_features)
    feats = np.zeros((n_features, dim))
    feats[:, 0] = dist * np.sin(angle)
    feats[:, 1] = radius - dist * np.cos(angle)
    if dim == 3:
        feats[:, 2] = rng.uniform(-2.0, 2.0, n_features)
    return World(dim, poses, {i + 1: feats[i] for i in range(n_features)})


def _random_spd(n: int, rng: np.random.Generator, scale: float = 100.0) -> FloatArray:
    a = rng.normal(size=(n, n))
    return scale * (a @ a.T / n + np.eye(n))


def _in_frame(world: World, frame: int, pose_ids: list[int], feature_ids: list[int]) -> FloatArray:
    d = world.dim
    t_f, a_f = world.poses[frame, :d], world.poses[frame, d:]
    parts = []
    for j in pose_ids:
        res = poses_to_frame(d, t_f, a_f, world.poses[j, :d], world.poses[j, d:])
        parts.append(np.concatenate([res.translations, res.angles]))
    for f in feature_ids:
        parts.append(points_to_frame(d, t_f, a_f, world.features[f]).points)
    return np.concatenate(parts) if parts else np.zeros(0)


def exact_map(
    world: World,
    frame: int,
    pose_ids: list[int],
    feature_ids: list[int],
    rng: np.random.Generator,
    end_id: int | None,
    name: str,
) -> LocalMap:
    """Return a noise-free map of the given poses and features in the frame of pose ``frame``."""
    ids = np.array(pose_ids + feature_ids, dtype=np.int64)
    kinds = np.array([POSE] * len(pose_ids) + [FEATURE] * len(feature_ids), dtype=np.int8)
    x = _in_frame(world, frame, pose_ids, feature_ids)
    return LocalMap(world.dim, frame, end_id, ids, kinds, x, _random_spd(x.size, rng), name=name)


def exact_local_maps(
    world: World,
    rng: np.random.Generator,
    poses_per_map: int = 1,
    sensor_range: float = 6.0,
    first_frame: int | None = None,
) -> list[LocalMap]:
    """Return noise-free pose-feature local maps along the trajectory.

    Map ``i`` is in the frame of its start pose and holds its other poses (the end pose last)
    and the features visible from any of its poses.

    Args:
        world: ground truth.
        rng: random generator for the information matrices.
        poses_per_map: robot steps per local map.
        sensor_range: feature visibility radius (m).
        first_frame: if given, the first map is expressed in the frame of this pose of its own
            (e.g. its end pose) instead of pose 0, which then becomes one of its variables.
    """
    n = len(world.poses) - 1
    maps = []
    for i, start in enumerate(range(0, n, poses_per_map)):
        end = min(start + poses_per_map, n)
        pose_ids = list(range(start + 1, end + 1))
        feats = sorted({f for j in range(start, end + 1) for f in world.visible(j, sensor_range)})
        frame = start
        if i == 0 and first_frame is not None and first_frame != start:
            frame = first_frame
            pose_ids = [j for j in range(start, end + 1) if j != frame]
        maps.append(exact_map(world, frame, pose_ids, feats, rng, end, f"exact_{i + 1}"))
    return maps


def exact_pose_graph_maps(world: World, rng: np.random.Generator, loop_every: int = 5, loop_span: int = 7) -> list[LocalMap]:
    """Return noise-free pose-only local maps: map ``i`` in the frame of pose ``i - 1`` holds pose
    ``i`` and, every ``loop_every`` maps, pose ``i + loop_span`` (a forward loop closure) and pose
    ``i - loop_span`` when it exists."""
    n = len(world.poses) - 1
    maps = []
    for i in range(1, n + 1):
        others = [i]
        if i % loop_every == 0:
            others += [j for j in (i - loop_span, i + loop_span) if 0 <= j <= n and j != i - 1]
        maps.append(exact_map(world, i - 1, others, [], rng, i, f"pg_{i}"))
    return maps


def _noisy(value: FloatArray, sigma: FloatArray, rng: np.random.Generator, dim: int, is_pose: bool) -> FloatArray:
    out = value + rng.normal(size=value.size) * sigma
    if is_pose:
        out[dim:] = wrap_angle(out[dim:])
    return out


def noisy_local_maps(
    world: World,
    rng: np.random.Generator,
    steps_per_map: int = 4,
    sensor_range: float = 6.0,
    sigma_odometry: tuple[float, float] = (0.02, 0.005),
    sigma_observation: float = 0.05,
) -> list[LocalMap]:
    """Return local maps built by Gauss-Newton from noisy odometry and observations.

    Each map is in the frame of its start pose, holds its end pose and the features observed
    from its poses; its intermediate poses are marginalised out (Schur complement).

    Args:
        world: ground truth.
        rng: noise generator.
        steps_per_map: odometry steps per local map.
        sensor_range: feature visibility radius (m).
        sigma_odometry: standard deviations of odometry translation (m) and angles (rad).
        sigma_observation: standard deviation of feature observations (m).
    """
    d = world.dim
    p = pose_size(d)
    sig_odo = np.concatenate([np.full(d, sigma_odometry[0]), np.full(angle_size(d), sigma_odometry[1])])
    sig_obs = np.full(d, sigma_observation)
    n = len(world.poses) - 1
    maps = []
    for i, start in enumerate(range(0, n, steps_per_map)):
        end = min(start + steps_per_map, n)
        meas: list[LocalMap] = []
        for j in range(start + 1, end + 1):
            rel = relative_pose(d, world.poses[j - 1], world.poses[j])
            z = _noisy(rel, sig_odo, rng, d, True)
            meas.append(LocalMap(d, j - 1, j, np.array([j]), np.array([POSE], np.int8), z, np.diag(sig_odo**-2)))
        observed: list[int] = []
        for j in range(start, end + 1):
            for f in world.visible(j, sensor_range):
                local = points_to_frame(d, world.poses[j, :d], world.poses[j, d:], world.features[f]).points
                z = _noisy(local, sig_obs, rng, d, False)
                meas.append(LocalMap(d, j, None, np.array([f]), np.array([FEATURE], np.int8), z, np.diag(sig_obs**-2)))
                if f not in observed:
                    observed.append(f)
        # initial guess: dead reckoning and first sightings, in the frame of the start pose
        pose_est = {start: np.zeros(p)}
        for m in meas[: end - start]:
            j = int(m.ids[0])
            pose_est[j] = compose_relative(d, pose_est[j - 1], m.x)
        feat_est: dict[int, FloatArray] = {}
        for m in meas[end - start :]:
            f = int(m.ids[0])
            if f not in feat_est:
                t, a = pose_est[m.frame_id][:d], pose_est[m.frame_id][d:]
                feat_est[f] = points_from_frame(d, t, a, m.x)
        pose_ids = list(range(start + 1, end + 1))
        ids = np.array(pose_ids + observed, dtype=np.int64)
        kinds = np.array([POSE] * len(pose_ids) + [FEATURE] * len(observed), dtype=np.int8)
        x0 = np.concatenate([pose_est[j] for j in pose_ids] + [feat_est[f] for f in observed])
        layout = LocalMap.trusted(d, start, end, ids, kinds, x0, np.eye(x0.size), f"noisy_{i + 1}")
        solved = gauss_newton(layout, meas).map
        keep_vars = np.array([len(pose_ids) - 1] + list(range(len(pose_ids), len(ids))), dtype=np.int64)
        drop_vars = np.arange(len(pose_ids) - 1, dtype=np.int64)
        keep = solved.scalar_index(keep_vars)
        drop = solved.scalar_index(drop_vars)
        info = solved.info_dense()
        if drop.size:
            schur = info[np.ix_(keep, drop)] @ np.linalg.solve(info[np.ix_(drop, drop)], info[np.ix_(drop, keep)])
            info_k = info[np.ix_(keep, keep)] - schur
        else:
            info_k = info
        maps.append(
            LocalMap(
                d, start, end, ids[keep_vars], kinds[keep_vars], solved.x[keep], 0.5 * (info_k + info_k.T),
                name=f"noisy_{i + 1}",
            )
        )
    return maps
