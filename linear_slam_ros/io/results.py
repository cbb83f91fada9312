"""Result files: the reference program's ``poses.txt`` and ``features.txt``, TUM trajectories.

:func:`write_map` takes any joined map the strategies produce and writes what it holds: a
pose map (:class:`~linear_slam_ros.core.local_map.LocalMap`) in the frame of a chosen pose, a
feature-only map (:class:`~linear_slam_ros.feature_only.maps.FeatureMap`) in its feature frame.
A new map type registers its writer here with ``@write_map.register``.

A TUM trajectory (:func:`write_tum`, the format of the TUM RGB-D benchmark and of ``evo``) has
one pose per line, ``timestamp tx ty tz qx qy qz qw`` (seconds, metres, unit quaternion of the
pose's orientation with ``qw >= 0``); 2D poses get ``tz = 0`` and a rotation about z. Offline
(:func:`write_result` with ``"tum"``) a pose's timestamp is its pose id: the benchmark datasets
carry no time, and the pose id is unique and increases along the trajectory.
"""

from __future__ import annotations

import functools
import json
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from linear_slam_ros.core.errors import ConfigError
from linear_slam_ros.core.frames import change_frame
from linear_slam_ros.core.geometry import pose_size
from linear_slam_ros.core.local_map import FEATURE, POSE, LocalMap
from linear_slam_ros.feature_only.maps import FeatureMap
from linear_slam_ros.io.datasets import check_origin_frame, write_features, write_poses
from linear_slam_ros.pose_graph.quaternions import angles_to_quaternions

POSE_FORMATS = ("reference", "tum")
"""Pose files :func:`write_result` writes: ``poses.txt`` (reference) and ``poses.tum`` (TUM)."""

TUM_HEADER = "# timestamp tx ty tz qx qy qz qw"
"""First line of a TUM file written here (a comment to TUM and evo readers)."""


def write_result(out_dir: Path, joined: LocalMap, origin_id: int, formats: Sequence[str] = ("reference",)) -> LocalMap:
    """Write the poses and (with features) ``features.txt`` in the frame of pose ``origin_id``.

    Args:
        out_dir: folder, created if missing.
        joined: the joined map.
        origin_id: pose whose frame everything is written in (it is written as the origin).
        formats: pose files to write, from :data:`POSE_FORMATS`: ``"reference"`` writes
            ``poses.txt``, ``"tum"`` writes ``poses.tum`` (:func:`write_tum_poses`).

    Returns:
        The map in the frame of ``origin_id`` (what was written).

    Raises:
        ConfigError: an unknown format.
    """
    unknown = sorted(set(formats) - set(POSE_FORMATS))
    if unknown:
        raise ConfigError(f"unknown pose file format(s) {unknown}; choose from {list(POSE_FORMATS)}")
    out_dir.mkdir(parents=True, exist_ok=True)
    in_origin = joined if joined.frame_id == origin_id else change_frame(joined, origin_id)
    if "reference" in formats:
        write_poses(out_dir / "poses.txt", in_origin, origin_id)
    if "tum" in formats:
        write_tum_poses(out_dir / "poses.tum", in_origin, origin_id)
    if (in_origin.kinds == FEATURE).any():
        write_features(out_dir / "features.txt", in_origin)
    return in_origin


def write_tum(path: Path, dim: int, stamps: npt.ArrayLike, poses: npt.ArrayLike) -> None:
    """Write a TUM trajectory: :data:`TUM_HEADER`, then ``timestamp tx ty tz qx qy qz qw`` per pose.

    Args:
        path: the file (replaced; its folder is created).
        dim: 2 or 3.
        stamps: ``(n,)`` timestamps (s), written with 9 decimals (nanoseconds).
        poses: ``(n, 3)`` ``x y phi`` or ``(n, 6)`` ``x y z alpha beta gamma`` (the datasets'
            convention, m and rad), written with 17 significant digits.
    """
    t = np.asarray(stamps, dtype=np.float64).reshape(-1)
    x = np.asarray(poses, dtype=np.float64).reshape(t.size, pose_size(dim))
    xyz = np.zeros((t.size, 3))
    xyz[:, :dim] = x[:, :dim]
    quats = angles_to_quaternions(dim, x[:, dim:])
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "w") as fh:
        fh.write(TUM_HEADER + "\n")
        for k in range(t.size):
            fh.write(f"{t[k]:.9f} " + " ".join(f"{v:.17g}" for v in (*xyz[k], *quats[k])) + "\n")


def write_tum_poses(path: Path, local_map: LocalMap, origin_id: int) -> None:
    """Write every pose of a map as a TUM trajectory stamped with its pose id (the origin pose too).

    The map must be in the frame of pose ``origin_id``, which is written as the identity.

    Raises:
        InvalidMapError: the map is not in the frame of ``origin_id``.
    """
    check_origin_frame(local_map, origin_id)
    index = np.flatnonzero(local_map.kinds == POSE)
    ids = np.concatenate([[origin_id], local_map.ids[index]]).astype(np.int64)
    values = np.zeros((ids.size, pose_size(local_map.dim)))
    for row, i in enumerate(index.tolist(), start=1):
        values[row] = local_map.x[local_map.scalar_slice(i)]
    order = np.argsort(ids, kind="stable")
    write_tum(path, local_map.dim, ids[order], values[order])


def write_tum_stamped(path: Path, local_map: LocalMap, origin_id: int, stamps: Mapping[int, float]) -> int:
    """Write the poses of a map that have a stamp as a TUM trajectory, in time order (the node's ``~/save_map``).

    Args:
        path: the file (replaced; its folder is created).
        local_map: the map, in the frame of pose ``origin_id``.
        origin_id: its frame pose (written as the identity when it has a stamp).
        stamps: ``{pose id: timestamp (s)}``: the node gives each joined submap's end pose the
            submap's message stamp. Poses without one (the first pose, a pose-graph chunk's inner
            poses, poses of a loaded map) are left out.

    Returns:
        The number of poses written.

    Raises:
        InvalidMapError: the map is not in the frame of ``origin_id``.
    """
    check_origin_frame(local_map, origin_id)
    ids = [pid for pid in stamps if pid == origin_id or local_map.has_pose(pid)]
    ids.sort(key=lambda pid: (stamps[pid], pid))
    poses = np.array([local_map.pose(pid) for pid in ids]).reshape(len(ids), pose_size(local_map.dim))
    write_tum(path, local_map.dim, [stamps[pid] for pid in ids], poses)
    return len(ids)


def write_feature_result(out_dir: Path, feature_map: FeatureMap) -> None:
    """Write ``features.txt`` (``id x y [z]`` per feature) in a feature-only map's frame."""
    out_dir.mkdir(parents=True, exist_ok=True)
    with open(out_dir / "features.txt", "w") as fh:
        for fid, pos in sorted(feature_map.positions().items()):
            fh.write(f"{fid} " + " ".join(f"{v:.17g}" for v in pos) + "\n")


@functools.singledispatch
def write_map(joined: object, out_dir: Path, origin_id: int | None) -> None:
    """Write a joined map's result files into ``out_dir``.

    Args:
        joined: the map (a type registered below).
        out_dir: folder, created if missing.
        origin_id: pose whose frame pose maps are written in (ignored by feature-only maps).

    Raises:
        TypeError: no writer is registered for the map's type.
    """
    raise TypeError(f"no result writer for {type(joined).__name__}")


@write_map.register
def _(joined: LocalMap, out_dir: Path, origin_id: int | None) -> None:
    write_result(out_dir, joined, joined.frame_id if origin_id is None else origin_id)


@write_map.register
def _(joined: FeatureMap, out_dir: Path, origin_id: int | None) -> None:
    write_feature_result(out_dir, joined)


def write_report(out_dir: Path, report: dict[str, Any]) -> None:
    """Write ``report.json`` (indented JSON) into ``out_dir``, created if missing."""
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / "report.json").write_text(json.dumps(report, indent=2) + "\n")
