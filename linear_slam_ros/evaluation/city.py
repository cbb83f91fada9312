"""City-sized synthetic streams with ground truth: seeded worlds far larger than the benchmark datasets.

Three families, each a function ``(size, seed) -> SyntheticStream`` (local maps in joining order
plus the :class:`~linear_slam_ros.evaluation.synthetic.World` they were measured from), registered
by name ``<family>-<size>``:

* ``city2d-N`` (:func:`city2d`): a 2D pose graph of ``N`` robot steps on a Manhattan grid of
  streets (the shape of manhattanOlson3500, larger): noisy odometry, and a loop-closure edge
  whenever the robot comes back near a pose it visited earlier. Emitted like the benchmark
  pose-only datasets: local map ``k`` is in the frame of pose ``k - 1`` and holds pose ``k`` and
  the earlier poses it closes loops to (a star, i.e. one ``pose_graph`` chunk).
* ``garage3d-N`` (:func:`garage3d`): the same in 3D: a multi-floor parking garage (grid of aisles
  per floor, stacked ramps between floors), ``N`` steps, loop closures on each floor.
* ``features2d-N`` (:func:`features2d`): a 2D pose-feature stream of ``N`` local maps (a park of
  trees, VicPark-like density): each local map is the Gauss-Newton optimum of the odometry and
  point observations of a few robot steps, in its start pose's frame, intermediate poses
  marginalised (as :func:`~linear_slam_ros.evaluation.synthetic.noisy_local_maps` builds them,
  but all submaps solved at once by vectorised Gauss-Newton: ``noisy_local_maps`` takes about
  56 ms per map, 280 s for 5,000).

Noise is Gaussian, additive on the measured relative pose ``(x, y[, z], angles)`` and point
coordinates, with exactly the information the maps carry, so the ground truth's χ² against the
maps follows a χ² law with as many degrees of freedom as the maps have scalars, and a linear
joined estimate has χ²/dof close to 1.

Importing this module registers the families as ``synthetic:<name>[@seed]`` sources of
:func:`linear_slam_ros.io.datasets.read_dataset` (generated on demand: a few seconds). Where it is
not imported (the offline CLI), ``read_dataset`` reads the stream's cache file instead,
``<dataset cache>/synthetic/<name>-seed<seed>.npz``, which :func:`cache`, ``make bags``,
``bag_from_dataset --synthetic`` and ``python -m linear_slam_ros.evaluation.city NAME...`` write
(the last also prints the streams' figures and, with ``--join dc online-dc``, their joining
figures).
"""

from __future__ import annotations

import argparse
import logging
import math
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import numpy.typing as npt
import scipy.sparse as sp
from scipy.spatial import cKDTree

from linear_slam_ros.core.errors import DatasetError
from linear_slam_ros.core.frames import change_frame
from linear_slam_ros.core.geometry import (
    angle_size,
    compose_relative,
    points_from_frame,
    points_to_frame,
    poses_to_frame,
    relative_pose,
    wrap_angle,
)
from linear_slam_ros.core.local_map import FEATURE, POSE, LocalMap
from linear_slam_ros.evaluation.metrics import rmse
from linear_slam_ros.evaluation.objective import chi2
from linear_slam_ros.evaluation.runner import run_join
from linear_slam_ros.evaluation.synthetic import World
from linear_slam_ros.io.datasets import (
    Dataset,
    MapKind,
    read_dataset_npz,
    register_synthetic,
    synthetic_cache_path,
    write_dataset_npz,
)

logger = logging.getLogger(__name__)

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]

GENERATOR_VERSION = 1
"""Bumped whenever a generator's output for a given (name, seed) changes; stale caches are regenerated."""

STANDARD_NAMES = ("city2d-20000", "garage3d-5000", "features2d-5000")
"""The city-sized streams ``make bags`` writes."""


@dataclass(frozen=True)
class SyntheticStream:
    """A generated stream of local maps with its ground truth.

    Attributes:
        name: ``<family>-<size>``, e.g. ``"city2d-20000"``.
        seed: the seed of the generator.
        kind: map kind (pose-only streams are emitted as ``pose_graph`` chunks in bags).
        world: ground truth: every robot pose (frame of pose 0; m, rad) and every feature (m).
        maps: the local maps in joining order (``maps[k]`` has sequence number ``k + 1``).
        n_loop_closures: loop-closure edges (pose graphs; 0 for pose-feature streams).
    """

    name: str
    seed: int
    kind: MapKind
    world: World
    maps: tuple[LocalMap, ...]
    n_loop_closures: int = 0

    def dataset(self) -> Dataset:
        """Return the stream as a :class:`~linear_slam_ros.io.datasets.Dataset` (what the CLI joins)."""
        return Dataset(self.name if self.seed == 0 else f"{self.name}@{self.seed}", self.kind, self.maps)

    def truth_map(self) -> LocalMap:
        """Return the ground truth as a map in the frame of pose 0: poses ``1..N``, then features.

        Its information is the identity (it is a reference, not an estimate): use it with
        :func:`linear_slam_ros.evaluation.metrics.rmse` and
        :func:`linear_slam_ros.evaluation.objective.chi2`.
        """
        w = self.world
        n = len(w.poses) - 1
        fids = np.array(sorted(w.features), dtype=np.int64)
        ids = np.concatenate([np.arange(1, n + 1, dtype=np.int64), fids])
        kinds = np.concatenate([np.full(n, POSE, np.int8), np.full(fids.size, FEATURE, np.int8)])
        feats = np.stack([w.features[int(f)] for f in fids]).reshape(-1) if fids.size else np.zeros(0)
        x = np.concatenate([w.poses[1:].reshape(-1), feats])
        return LocalMap.trusted(w.dim, 0, n, ids, kinds, x, sp.identity(x.size, format="csr"), name=f"{self.name} truth")

    def loop_closures_per_pose(self) -> float:
        """Loop-closure edges per robot pose (manhattanOlson3500: 0.56; sphere2500: 0.98)."""
        return self.n_loop_closures / max(len(self.world.poses) - 1, 1)


# ---------------------------------------------------------------------------- pose graphs


@dataclass(frozen=True)
class PoseGraphNoise:
    """Standard deviations of the relative-pose measurements: translation (m) and angles (rad)."""

    odometry: tuple[float, float] = (0.05, 0.005)
    loop: tuple[float, float] = (0.1, 0.01)


@dataclass(frozen=True)
class LoopPolicy:
    """When a loop closure is detected.

    Attributes:
        radius: a pose within this distance (m) of an earlier pose may close a loop to it.
        min_gap: ... if the earlier pose is at least this many steps older.
        probability: chance that a pose with such earlier poses closes a loop at all.
        max_per_pose: most loop closures measured from one pose (random among the candidates).
    """

    radius: float = 1.5
    min_gap: int = 30
    probability: float = 0.75
    max_per_pose: int = 1


def _sigmas(dim: int, sigma: tuple[float, float]) -> FloatArray:
    return np.concatenate([np.full(dim, sigma[0]), np.full(angle_size(dim), sigma[1])])


def loop_closures(positions: FloatArray, rng: np.random.Generator, policy: LoopPolicy) -> tuple[IntArray, IntArray]:
    """Return loop closures ``(frm, to)``: pose ``frm`` measures the earlier pose ``to``.

    Every pair within ``policy.radius`` (m) and at least ``policy.min_gap`` steps apart is a
    candidate; each pose with candidates draws whether it closes loops, then up to
    ``max_per_pose`` of its candidates at random. The last pose closes none (it starts no map).
    Pairs come out sorted by ``frm``, then ``to``.
    """
    pairs = cKDTree(positions).query_pairs(policy.radius, output_type="ndarray").astype(np.int64)
    if pairs.size == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    lo, hi = pairs.min(axis=1), pairs.max(axis=1)
    ok = (hi - lo >= policy.min_gap) & (hi < len(positions) - 1)
    frm, to = hi[ok], lo[ok]
    order = np.lexsort((rng.random(frm.size), frm))
    frm, to = frm[order], to[order]
    first = np.r_[True, frm[1:] != frm[:-1]]
    start = np.maximum.accumulate(np.where(first, np.arange(frm.size), 0))
    rank = np.arange(frm.size) - start
    poses_with = np.unique(frm)
    closes = poses_with[rng.random(poses_with.size) < policy.probability]
    keep = (rank < policy.max_per_pose) & np.isin(frm, closes)
    frm, to = frm[keep], to[keep]
    order = np.lexsort((to, frm))
    return frm[order], to[order]


def pose_graph_maps(
    world: World, rng: np.random.Generator, noise: PoseGraphNoise, policy: LoopPolicy, name: str
) -> tuple[list[LocalMap], int]:
    """Return the pose-only local maps of a trajectory and the number of loop closures.

    Map ``k`` (``k = 1..N``, named ``<name>_<k>``) is in the frame of pose ``k - 1`` and holds
    pose ``k`` (odometry) and the earlier poses that pose ``k - 1`` closes loops to; its
    estimate is the noisy measurements (truth plus Gaussian noise of ``noise``), its information
    block diagonal with the inverse variances. The end pose is pose ``k``. The maps are valid by
    construction and built unvalidated (:meth:`LocalMap.trusted`; validating 20,000 maps takes
    longer than generating them); readers and the node validate what they receive.
    """
    d = world.dim
    n = len(world.poses) - 1
    frm_l, to_l = loop_closures(world.poses[:, :d], rng, policy)
    frm = np.concatenate([np.arange(n, dtype=np.int64), frm_l])
    to = np.concatenate([np.arange(1, n + 1, dtype=np.int64), to_l])
    sig = np.concatenate([np.tile(_sigmas(d, noise.odometry), (n, 1)), np.tile(_sigmas(d, noise.loop), (frm_l.size, 1))])
    z = relative_pose(d, world.poses[frm], world.poses[to]) + rng.normal(size=sig.shape) * sig
    z[:, d:] = wrap_angle(z[:, d:])
    order = np.argsort(frm, kind="stable")  # per frame: the odometry edge first, then loops by id
    frm, to, z, sig = frm[order], to[order], z[order], sig[order]
    bounds = np.searchsorted(frm, np.arange(n + 1))
    maps = []
    for k in range(1, n + 1):
        a, b = int(bounds[k - 1]), int(bounds[k])
        m = b - a
        info = np.diag((sig[a:b] ** -2.0).reshape(-1))
        kinds = np.full(m, POSE, np.int8)
        maps.append(LocalMap.trusted(d, k - 1, k, to[a:b], kinds, z[a:b].reshape(-1), info, name=f"{name}_{k}"))
    return maps, int(frm_l.size)


_HEADINGS = np.array([[1.0, 0.0], [0.0, 1.0], [-1.0, 0.0], [0.0, -1.0]])  # E, N, W, S


def city_trajectory(n_poses: int, rng: np.random.Generator, block: int = 10, blocks: int | None = None) -> FloatArray:
    """Return ``n_poses + 1`` 2D poses of a drive on a Manhattan grid, pose 0 at the origin.

    The robot drives 1 m a step along the streets of a ``blocks x blocks`` grid of ``block`` m
    blocks; at each intersection it goes straight (probability 1/2), left or right (1/4 each),
    never leaving the grid (a U-turn only in a dead end). Each street traversal keeps its lane:
    a lateral offset drawn in [-0.3, 0.3] m. Default ``blocks``: about ``sqrt(N / (6 block))``,
    so each street is driven about three times.
    """
    g = blocks if blocks is not None else max(2, round(math.sqrt(n_poses / (6 * block))))
    node = np.array([g // 2, g // 2])
    heading = 0
    out = [np.array([node[0] * block, node[1] * block, 0.0])]
    steps = np.arange(1, block + 1, dtype=np.float64)[:, None]
    total = 0
    while total < n_poses:
        options = [(heading + turn) % 4 for turn in (0, 1, 3)]
        weights = np.array([0.5, 0.25, 0.25])
        inside = np.array([np.all((node + _HEADINGS[h]).astype(int) >= 0) and np.all(node + _HEADINGS[h] <= g) for h in options])
        if not inside.any():
            choice = (heading + 2) % 4
        else:
            w = weights * inside
            choice = options[int(rng.choice(3, p=w / w.sum()))]
        direction = _HEADINGS[choice]
        normal = np.array([-direction[1], direction[0]])
        lane = rng.uniform(-0.3, 0.3)
        xy = node * block + steps * direction + lane * normal
        phi = np.full((block, 1), math.atan2(direction[1], direction[0]))
        out.append(np.hstack([xy, phi]))
        node = (node + direction).astype(int)
        heading = choice
        total += block
    poses = np.vstack(out)[: n_poses + 1]
    return _to_first_frame(2, poses)


def _to_first_frame(dim: int, poses: FloatArray) -> FloatArray:
    """Return ``poses`` seen from ``poses[0]`` (pose 0 becomes exactly the origin)."""
    rel = relative_pose(dim, np.broadcast_to(poses[0], poses.shape), poses)
    rel[0] = 0.0
    return rel


def city2d(
    n_poses: int = 20000,
    seed: int = 0,
    noise: PoseGraphNoise | None = None,
    policy: LoopPolicy | None = None,
) -> SyntheticStream:
    """Return ``city2d-<n_poses>``: a Manhattan-grid 2D pose graph of ``n_poses`` steps.

    Args:
        n_poses: robot steps (1 m each); the stream has ``n_poses`` local maps.
        seed: seed of the trajectory, the loop closures and the noise.
        noise: measurement standard deviations (default :class:`PoseGraphNoise`).
        policy: loop-closure detection (default :class:`LoopPolicy`).
    """
    rng = np.random.default_rng([seed, 2, 20000])
    name = f"city2d-{n_poses}"
    world = World(2, city_trajectory(n_poses, rng), {})
    maps, n_loops = pose_graph_maps(world, rng, noise or PoseGraphNoise(), policy or LoopPolicy(), name)
    return SyntheticStream(name, seed, MapKind.PG2D, world, tuple(maps), n_loops)


def garage_trajectory(
    n_poses: int, rng: np.random.Generator, floors: int | None = None, aisles: int = 4, block: int = 10, height: float = 3.0
) -> FloatArray:
    """Return ``n_poses + 1`` 3D poses ``x y z alpha beta gamma`` of a drive through a parking garage.

    Each floor is a grid of ``aisles x aisles`` blocks of ``block`` m, ``height`` m above the one
    below; between floors ``f`` and ``f + 1`` a straight ramp replaces the aisle from corner
    ``(aisles, 0)`` to ``(aisles, 1)`` (the ramps stack). The robot drives 1 m a step (a ramp
    step is a little longer), choosing at random among the aisles at each junction but the one
    it came from. ``alpha`` is the heading, ``beta`` the pitch (negative uphill with the
    datasets' ``R = RX(gamma) RY(beta) RZ(alpha)``), ``gamma`` (roll) 0. Default ``floors``:
    enough for about four passes of each aisle, at least 2.
    """
    per_floor = 2 * aisles * (aisles + 1) * block
    n_floors = floors if floors is not None else max(2, min(12, round(n_poses / (4 * per_floor))))
    coords: dict[tuple[int, int, int], FloatArray] = {}
    adjacency: dict[tuple[int, int, int], list[tuple[int, int, int]]] = {}

    def link(a: tuple[int, int, int], b: tuple[int, int, int]) -> None:
        adjacency.setdefault(a, []).append(b)
        adjacency.setdefault(b, []).append(a)

    for f in range(n_floors):
        for i in range(aisles + 1):
            for j in range(aisles + 1):
                coords[(f, i, j)] = np.array([i * block, j * block, f * height], dtype=np.float64)
                if i < aisles:
                    link((f, i, j), (f, i + 1, j))
                ramp_slot = i == aisles and j == 0 and f < n_floors - 1
                if j < aisles and not ramp_slot:
                    link((f, i, j), (f, i, j + 1))
        if f < n_floors - 1:
            link((f, aisles, 0), (f + 1, aisles, 1))
    node = (0, aisles // 2, aisles // 2)
    previous: tuple[int, int, int] | None = None
    steps = np.arange(1, block + 1, dtype=np.float64)[:, None] / block
    out = [np.concatenate([coords[node], np.zeros(3)])]
    total = 0
    while total < n_poses:
        options = [b for b in adjacency[node] if b != previous] or adjacency[node]
        nxt = options[int(rng.integers(len(options)))]
        delta = coords[nxt] - coords[node]
        alpha = math.atan2(delta[1], delta[0])
        beta = -math.atan2(delta[2], math.hypot(delta[0], delta[1]))
        xyz = coords[node] + steps * delta
        angles = np.tile([alpha, beta, 0.0], (block, 1))
        out.append(np.hstack([xyz, angles]))
        previous, node = node, nxt
        total += block
    poses = np.vstack(out)[: n_poses + 1]
    return _to_first_frame(3, poses)


def garage3d(
    n_poses: int = 5000,
    seed: int = 0,
    noise: PoseGraphNoise | None = None,
    policy: LoopPolicy | None = None,
) -> SyntheticStream:
    """Return ``garage3d-<n_poses>``: a multi-floor parking-garage 3D pose graph of ``n_poses`` steps.

    Args:
        n_poses: robot steps (about 1 m each); the stream has ``n_poses`` local maps.
        seed: seed of the trajectory, the loop closures and the noise.
        noise: measurement standard deviations (default :class:`PoseGraphNoise`; angles rad).
        policy: loop-closure detection (default :class:`LoopPolicy` with probability 0.9:
            about one loop closure a pose, like sphere2500).
    """
    rng = np.random.default_rng([seed, 3, 5000])
    name = f"garage3d-{n_poses}"
    world = World(3, garage_trajectory(n_poses, rng), {})
    loops = policy or LoopPolicy(probability=0.9, max_per_pose=2)
    maps, n_loops = pose_graph_maps(world, rng, noise or PoseGraphNoise(), loops, name)
    return SyntheticStream(name, seed, MapKind.PG3D, world, tuple(maps), n_loops)


# ---------------------------------------------------------------------------- pose-feature stream


def park_world(
    n_steps: int, rng: np.random.Generator, density: float = 0.03, side: float | None = None, max_turn: float = 0.2
) -> World:
    """Return a 2D park: trees (point features, ids 1..) and a drive of ``n_steps`` 1 m steps among them.

    Trees are uniform with ``density`` per m² over a square of ``side`` m (default
    ``max(40, 2.2 sqrt(n_steps))``, so the drive covers the park several times) plus a 15 m
    margin; the robot heads for random waypoints, turning at most ``max_turn`` rad a step.
    Pose 0 is the origin.
    """
    s = side if side is not None else max(40.0, 2.2 * math.sqrt(n_steps))
    margin = 15.0
    n_trees = int(rng.poisson(density * (s + 2 * margin) ** 2))
    trees = rng.uniform(-margin, s + margin, size=(n_trees, 2))
    poses = np.zeros((n_steps + 1, 3))
    t = np.array([s / 2, s / 2])
    heading = 0.0
    goal = rng.uniform(0.1 * s, 0.9 * s, 2)
    poses[0] = [t[0], t[1], heading]
    for k in range(1, n_steps + 1):
        if np.hypot(*(goal - t)) < 5.0:
            goal = rng.uniform(0.1 * s, 0.9 * s, 2)
        want = math.atan2(goal[1] - t[1], goal[0] - t[0])
        heading = float(wrap_angle(heading + np.clip(wrap_angle(want - heading), -max_turn, max_turn)))
        t = t + np.array([math.cos(heading), math.sin(heading)])
        poses[k] = [t[0], t[1], heading]
    rel = _to_first_frame(2, poses)
    local_trees = points_to_frame(2, poses[0, :2], poses[0, 2:], trees).points
    return World(2, rel, {i + 1: local_trees[i] for i in range(n_trees)})


@dataclass(frozen=True)
class FeatureMeasurements:
    """The raw measurements of a pose-feature stream (2D), grouped by local map.

    Local map ``i`` (``i = 0..M-1``) spans poses ``s i .. s (i + 1)`` (``s = steps_per_map``).

    Attributes:
        steps_per_map: ``s``.
        odometry: ``(M, s, 3)``: step ``q`` of map ``i``, pose ``s i + q + 1`` seen from pose
            ``s i + q`` (m, rad).
        sigma_odometry: ``(3,)`` standard deviations of the odometry (m, m, rad).
        obs_map: ``(K,)`` map of each observation.
        obs_pose: ``(K,)`` observing pose (a robot pose id).
        obs_feature: ``(K,)`` observed feature id.
        obs: ``(K, 2)`` the feature seen from the observing pose (m).
        sigma_observation: standard deviation of each observed coordinate (m).
    """

    steps_per_map: int
    odometry: FloatArray
    sigma_odometry: FloatArray
    obs_map: IntArray
    obs_pose: IntArray
    obs_feature: IntArray
    obs: FloatArray
    sigma_observation: float

    @property
    def n_maps(self) -> int:
        """Number of local maps ``M``."""
        return int(self.odometry.shape[0])


def measure_features(
    world: World,
    rng: np.random.Generator,
    steps_per_map: int = 4,
    sensor_range: float = 12.0,
    sigma_odometry: tuple[float, float] = (0.02, 0.005),
    sigma_observation: float = 0.05,
) -> FeatureMeasurements:
    """Return noisy odometry and observations of a 2D world, grouped into local maps.

    The sensor sees the trees within ``sensor_range`` m in front of the robot (local ``x > 0``,
    a 180° laser like Victoria Park's). Map ``i`` holds the scans of its poses ``s i + 1 .. s (i
    + 1)`` (map 0 also pose 0's), so each scan is used once.
    """
    n = len(world.poses) - 1
    s = steps_per_map
    if n % s:
        raise ValueError(f"{n} steps do not split into local maps of {s} steps")
    m = n // s
    sig_odo = _sigmas(2, sigma_odometry)
    odo = relative_pose(2, world.poses[:-1], world.poses[1:]) + rng.normal(size=(n, 3)) * sig_odo
    odo[:, 2] = wrap_angle(odo[:, 2])
    fids = np.array(sorted(world.features), dtype=np.int64)
    fpos = np.stack([world.features[int(f)] for f in fids]) if fids.size else np.zeros((0, 2))
    tree = cKDTree(fpos)
    hits: Sequence[Sequence[int]] = tree.query_ball_point(world.poses[:, :2], sensor_range)  # type: ignore[assignment]
    pose_of = np.repeat(np.arange(n + 1), [len(h) for h in hits]).astype(np.int64)
    feat_idx = np.concatenate([np.asarray(h, dtype=np.int64) for h in hits])
    local = points_to_frame(2, world.poses[pose_of, :2], world.poses[pose_of, 2:], fpos[feat_idx]).points
    front = local[:, 0] > 0.0
    pose_of, feat_idx, local = pose_of[front], feat_idx[front], local[front]
    order = np.lexsort((fids[feat_idx], pose_of))
    pose_of, feat_idx, local = pose_of[order], feat_idx[order], local[order]
    obs = local + rng.normal(size=local.shape) * sigma_observation
    obs_map = np.maximum(pose_of - 1, 0) // s
    return FeatureMeasurements(
        s, odo.reshape(m, s, 3), sig_odo, obs_map.astype(np.int64), pose_of, fids[feat_idx], obs, sigma_observation
    )


def _accumulate(
    hess: FloatArray,
    grad: FloatArray,
    cols: IntArray,
    owner_off: IntArray,
    owner_n: IntArray,
    hess_off: IntArray,
    jac: FloatArray,
    res: FloatArray,
    weight: FloatArray,
) -> None:
    """Add ``J^T W J`` and ``J^T W r`` of a batch of residual blocks to per-map dense systems.

    Args:
        hess: flat buffer of every map's dense ``n_i x n_i`` normal matrix (at ``hess_off[i]``).
        grad: gradient, indexed by global unknown.
        cols: ``(B, k)`` global unknown of each Jacobian column, -1 for a fixed one (the frame pose).
        owner_off, owner_n, hess_off: per block, its map's first unknown, size and buffer offset.
        jac: ``(B, r, k)`` Jacobians; res: ``(B, r)`` residuals; weight: ``(r,)`` inverse variances.
    """
    valid = cols >= 0
    jac = np.where(valid[:, None, :], jac, 0.0)
    jw = jac * weight[None, :, None]
    block = np.einsum("bri,brj->bij", jw, jac)
    g = np.einsum("bri,br->bi", jw, res)
    loc = np.where(valid, cols - owner_off[:, None], 0)
    flat = hess_off[:, None, None] + loc[:, :, None] * owner_n[:, None, None] + loc[:, None, :]
    both = valid[:, :, None] & valid[:, None, :]
    hess += np.bincount(flat[both], weights=block[both], minlength=hess.size)
    grad += np.bincount(cols[valid], weights=g[valid], minlength=grad.size)


def feature_local_maps(meas: FeatureMeasurements, name: str = "features2d", tolerance: float = 1e-10) -> list[LocalMap]:
    """Return the local maps of ``meas``: each the Gauss-Newton optimum of its measurements.

    Map ``i`` is in the frame of pose ``s i``; its unknowns are its poses ``s i + 1 .. s (i + 1)``
    and the features it observes. All maps are solved together (their normal equations are
    independent dense blocks, solved in batches of equal size) until the largest step is below
    ``tolerance``; the information ``J^T W J`` is taken at the optimum and the intermediate
    poses are marginalised out (Schur complement). The result holds the end pose ``s (i + 1)``
    (first) and the features (by id): exactly what
    :func:`~linear_slam_ros.evaluation.synthetic.noisy_local_maps` computes map by map.
    """
    s, m = meas.steps_per_map, meas.n_maps
    # unknowns of map i: s poses (3 each), then its features in id order (2 each)
    key = meas.obs_map * (int(meas.obs_feature.max(initial=0)) + 1) + meas.obs_feature
    ukeys, first, inverse = np.unique(key, return_index=True, return_inverse=True)
    feat_map = meas.obs_map[first]
    nf = np.bincount(feat_map, minlength=m)
    n_i = 3 * s + 2 * nf
    off = np.concatenate([[0], np.cumsum(n_i)[:-1]]).astype(np.int64)
    h_off = np.concatenate([[0], np.cumsum(n_i * n_i)[:-1]]).astype(np.int64)
    rank = np.arange(ukeys.size) - np.searchsorted(feat_map, feat_map)
    feat_col = off[feat_map] + 3 * s + 2 * rank  # global first unknown of each (map, feature)
    obs_col = feat_col[inverse]
    obs_q = meas.obs_pose - s * meas.obs_map  # 0..s, 0 = the frame pose
    total = int(n_i.sum())

    def pose_cols(i: IntArray, q: IntArray) -> IntArray:
        base = off[i] + 3 * (q - 1)
        return np.where((q >= 1)[:, None], base[:, None] + np.arange(3), -1)

    # initial guess: dead reckoning, features from their first sighting
    x = np.zeros(total)
    poses = np.zeros((m, s + 1, 3))
    for q in range(1, s + 1):
        poses[:, q] = compose_relative(2, poses[:, q - 1], meas.odometry[:, q - 1])
    x[(off[:, None] + np.arange(3 * s)).reshape(-1)] = poses[:, 1:].reshape(-1)
    seen = poses[meas.obs_map[first], obs_q[first]]
    x[feat_col[:, None] + np.arange(2)] = points_from_frame(2, seen[:, :2], seen[:, 2:], meas.obs[first])

    maps_i = np.repeat(np.arange(m), s)
    steps_q = np.tile(np.arange(1, s + 1), m)
    odo_cols = np.hstack([pose_cols(maps_i, steps_q - 1), pose_cols(maps_i, steps_q)])
    obs_cols = np.hstack([pose_cols(meas.obs_map, obs_q), obs_col[:, None] + np.arange(2)])
    w_odo = meas.sigma_odometry**-2.0
    w_obs = np.full(2, meas.sigma_observation**-2.0)

    def normal_equations(x: FloatArray) -> tuple[FloatArray, FloatArray]:
        pose_x = np.zeros((m, s + 1, 3))
        pose_x[:, 1:] = x[(off[:, None] + np.arange(3 * s)).reshape(-1)].reshape(m, s, 3)
        a, b = pose_x[:, :-1].reshape(-1, 3), pose_x[:, 1:].reshape(-1, 3)
        rel = poses_to_frame(2, a[:, :2], a[:, 2:], b[:, :2], b[:, 2:])
        r_odo = np.concatenate([rel.translations, rel.angles], -1) - meas.odometry.reshape(-1, 3)
        r_odo[:, 2] = wrap_angle(r_odo[:, 2])
        j_odo = np.concatenate([rel.d_frame, rel.d_pose], -1)
        obs_pose = pose_x[meas.obs_map, obs_q]
        pts = points_to_frame(2, obs_pose[:, :2], obs_pose[:, 2:], x[obs_col[:, None] + np.arange(2)])
        r_obs = pts.points - meas.obs
        j_obs = np.concatenate([pts.d_frame, pts.d_point], -1)
        hess, grad = np.zeros(int(h_off[-1] + n_i[-1] ** 2)), np.zeros(total)
        _accumulate(hess, grad, odo_cols, off[maps_i], n_i[maps_i], h_off[maps_i], j_odo, r_odo, w_odo)
        _accumulate(hess, grad, obs_cols, off[meas.obs_map], n_i[meas.obs_map], h_off[meas.obs_map], j_obs, r_obs, w_obs)
        return hess, grad

    groups = [np.flatnonzero(n_i == size) for size in np.unique(n_i)]

    def blocks(hess: FloatArray, sel: IntArray, size: int) -> FloatArray:
        return hess[h_off[sel][:, None] + np.arange(size * size)].reshape(-1, size, size)

    for _ in range(50):
        hess, grad = normal_equations(x)
        step = np.zeros(total)
        for sel in groups:
            size = int(n_i[sel[0]])
            idx = off[sel][:, None] + np.arange(size)
            step[idx] = np.linalg.solve(blocks(hess, sel, size), -grad[idx][..., None])[..., 0]
        x += step
        angle_cols = (off[:, None] + 3 * np.arange(s) + 2).reshape(-1)
        x[angle_cols] = wrap_angle(x[angle_cols])
        if np.max(np.abs(step)) < tolerance:
            break
    else:  # pragma: no cover - the maps are small and well started
        raise DatasetError(f"{name}: Gauss-Newton of the local maps did not converge")
    hess, _ = normal_equations(x)

    out: list[LocalMap | None] = [None] * m
    fid_sorted = meas.obs_feature[first]
    for sel in groups:
        size = int(n_i[sel[0]])
        h = blocks(hess, sel, size)
        drop, keep = np.arange(3 * (s - 1)), np.arange(3 * (s - 1), size)
        h_kk = h[:, keep[:, None], keep]
        if drop.size:
            h_kd = h[:, keep[:, None], drop]
            h_kk = h_kk - h_kd @ np.linalg.solve(h[:, drop[:, None], drop], np.swapaxes(h_kd, 1, 2))
        h_kk = 0.5 * (h_kk + np.swapaxes(h_kk, 1, 2))
        for row, i in enumerate(sel.tolist()):
            fids = fid_sorted[feat_map == i] if nf[i] else np.zeros(0, np.int64)
            ids = np.concatenate([[s * (i + 1)], fids]).astype(np.int64)
            kinds = np.concatenate([[POSE], np.full(fids.size, FEATURE)]).astype(np.int8)
            xi = x[off[i] + 3 * (s - 1) : off[i] + size]
            out[i] = LocalMap.trusted(2, s * i, s * (i + 1), ids, kinds, xi.copy(), h_kk[row], name=f"{name}_{i + 1}")
    return [mp for mp in out if mp is not None]


def features2d(n_maps: int = 5000, seed: int = 0, steps_per_map: int = 4) -> SyntheticStream:
    """Return ``features2d-<n_maps>``: a 2D pose-feature stream of ``n_maps`` local maps in a park.

    Args:
        n_maps: local maps; the drive has ``steps_per_map * n_maps`` steps of 1 m.
        seed: seed of the park, the drive and the noise.
        steps_per_map: robot steps per local map (their intermediate poses are marginalised).
    """
    rng = np.random.default_rng([seed, 4, 5000])
    name = f"features2d-{n_maps}"
    world = park_world(steps_per_map * n_maps, rng)
    meas = measure_features(world, rng, steps_per_map)
    observed = set(np.unique(meas.obs_feature).tolist())
    world = World(2, world.poses, {f: p for f, p in world.features.items() if f in observed})
    return SyntheticStream(name, seed, MapKind.PF2D, world, tuple(feature_local_maps(meas, name)))


# ---------------------------------------------------------------------------- registry and cache

FAMILIES: dict[str, Callable[[int, int], SyntheticStream]] = {
    "city2d": lambda size, seed: city2d(size, seed),
    "garage3d": lambda size, seed: garage3d(size, seed),
    "features2d": lambda size, seed: features2d(size, seed),
}
"""Generator of each family, called with ``(size, seed)``."""


def _family_and_size(name: str) -> tuple[str, int]:
    family, _, size = name.rpartition("-")
    if family not in FAMILIES or not size.isdigit() or int(size) < 1:
        raise DatasetError(f"unknown synthetic stream {name!r}: expected <family>-<size> with family in {sorted(FAMILIES)}")
    return family, int(size)


def generate(name: str, seed: int = 0) -> SyntheticStream:
    """Generate stream ``name`` (``<family>-<size>``, e.g. ``"city2d-20000"``) with ``seed``, uncached.

    Raises:
        DatasetError: an unknown family or a malformed name.
    """
    family, size = _family_and_size(name)
    return FAMILIES[family](size, seed)


def _save(stream: SyntheticStream, path: Path) -> None:
    fids = np.array(sorted(stream.world.features), dtype=np.int64)
    feats = np.stack([stream.world.features[int(f)] for f in fids]) if fids.size else np.zeros((0, stream.world.dim))
    write_dataset_npz(
        path,
        stream.dataset(),
        {
            "generator_version": np.array(GENERATOR_VERSION),
            "seed": np.array(stream.seed),
            "n_loop_closures": np.array(stream.n_loop_closures),
            "truth_poses": stream.world.poses,
            "truth_feature_ids": fids,
            "truth_features": feats,
        },
    )


def is_cached(name: str, seed: int = 0, cache_dir: Path | None = None) -> bool:
    """Return whether the cache holds stream ``name`` with ``seed`` from this generator version."""
    path = synthetic_cache_path(name, seed, cache_dir)
    try:
        with np.load(path, allow_pickle=False) as data:  # reads only the entry asked for
            return int(data["generator_version"]) == GENERATOR_VERSION
    except (OSError, KeyError, ValueError):
        return False


def cache(stream: SyntheticStream, cache_dir: Path | None = None) -> Path:
    """Write ``stream`` (maps and ground truth) to its cache file unless it is there already; return the path.

    The cache lets :func:`linear_slam_ros.io.datasets.read_dataset` read ``synthetic:NAME[@SEED]``
    where no generator is registered (the offline CLI).
    """
    path = synthetic_cache_path(stream.name, stream.seed, cache_dir)
    if not is_cached(stream.name, stream.seed, cache_dir):
        _save(stream, path)
    return path


def read_cached(name: str, seed: int = 0, cache_dir: Path | None = None) -> SyntheticStream:
    """Return stream ``name`` with ``seed`` from its cache file (every map validated on reading).

    Raises:
        DatasetError: no cache file of this generator version.
    """
    path = synthetic_cache_path(name, seed, cache_dir)
    if not is_cached(name, seed, cache_dir):
        raise DatasetError(f"{path}: no cache of {name} (seed {seed}) by generator version {GENERATOR_VERSION}")
    dataset, extra = read_dataset_npz(path)
    fids, feats = extra["truth_feature_ids"], extra["truth_features"].astype(np.float64)
    world = World(dataset.dim, extra["truth_poses"].astype(np.float64), {int(f): feats[i] for i, f in enumerate(fids)})
    return SyntheticStream(name, seed, dataset.kind, world, dataset.maps, int(extra["n_loop_closures"]))


def _dataset_source(name: str, seed: int, cache_dir: Path | None) -> Dataset:
    """The registered source: generating is faster than reading the cache (which validates every map)."""
    del cache_dir
    return generate(name, seed).dataset()


for _family in FAMILIES:
    register_synthetic(_family, _dataset_source)


def describe(stream: SyntheticStream) -> dict[str, float | int | str]:
    """Return the stream's size figures (what ``python -m linear_slam_ros.evaluation.city`` prints)."""
    scalars = sum(mp.x.size for mp in stream.maps)
    return {
        "name": stream.name,
        "seed": stream.seed,
        "kind": stream.kind.value,
        "n_maps": len(stream.maps),
        "n_poses": len(stream.world.poses) - 1,
        "n_features": len(stream.world.features),
        "n_loop_closures": stream.n_loop_closures,
        "loop_closures_per_pose": round(stream.loop_closures_per_pose(), 4),
        "map_scalars_total": scalars,
        "map_scalars_max": max(mp.x.size for mp in stream.maps),
    }


def join_figures(stream: SyntheticStream, method: str = "dc") -> dict[str, float | int | str]:
    """Join a stream and return how good the result is against its maps and its ground truth.

    Returns:
        ``method``, ``seconds`` (joining only), ``chi2`` of the joined map against all local
        maps, ``dof`` (map scalars minus state scalars: the χ² expected of a consistent linear
        estimate), ``chi2_per_dof``, ``truth_chi2_per_scalar`` (the ground truth's χ² over the
        map scalars: about 1 when the maps' information matches their errors), and the RMSE
        of pose and feature positions against the ground truth (m; frame of pose 0).
    """
    run = run_join(stream.maps, method)
    result = run.result if run.result.frame_id == 0 else change_frame(run.result, 0)
    truth = stream.truth_map()
    scalars = sum(mp.x.size for mp in stream.maps)
    value = chi2(result, stream.maps)
    dof = scalars - result.x.size
    out: dict[str, float | int | str] = {
        "method": str(method),
        "seconds": round(run.seconds, 3),
        "chi2": round(value, 2),
        "dof": dof,
        "chi2_per_dof": round(value / dof, 4),
        "truth_chi2_per_scalar": round(chi2(truth, stream.maps) / scalars, 4),
        "rmse_pose_m": float(f"{rmse(result, truth, POSE):.4g}"),
    }
    if stream.kind.has_features:
        out["rmse_feature_m"] = float(f"{rmse(result, truth, FEATURE):.4g}")
    return out


def main(argv: Sequence[str] | None = None) -> int:
    """Generate (and cache) synthetic streams; print their figures and generation times."""
    ap = argparse.ArgumentParser(prog="python -m linear_slam_ros.evaluation.city", description=main.__doc__)
    ap.add_argument("names", nargs="*", default=list(STANDARD_NAMES), help=f"streams (default {' '.join(STANDARD_NAMES)})")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--no-cache", action="store_true", help="do not write the cache")
    ap.add_argument("--join", nargs="*", default=[], metavar="METHOD", help="also join by these methods (dc, online-dc, ...)")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    for name in args.names:
        try:
            start = time.perf_counter()
            stream = generate(name, args.seed)
            seconds = time.perf_counter() - start
            if not args.no_cache:
                logger.info("%s: cached in %s", name, cache(stream))
        except DatasetError as exc:
            logger.error("%s", exc)
            return 2
        print({**describe(stream), "seconds": round(seconds, 2)}, flush=True)
        for method in args.join:
            print(join_figures(stream, method), flush=True)
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
