"""Result files in the reference program's format: ``poses.txt`` and ``features.txt``.

:func:`write_map` takes any joined map the strategies produce and writes what it holds: a
pose map (:class:`~linear_slam_ros.core.local_map.LocalMap`) in the frame of a chosen pose, a
feature-only map (:class:`~linear_slam_ros.feature_only.maps.FeatureMap`) in its feature frame.
A new map type registers its writer here with ``@write_map.register``.
"""

from __future__ import annotations

import functools
import json
from pathlib import Path
from typing import Any

from linear_slam_ros.core.frames import change_frame
from linear_slam_ros.core.local_map import FEATURE, LocalMap
from linear_slam_ros.feature_only.maps import FeatureMap
from linear_slam_ros.io.datasets import write_features, write_poses


def write_result(out_dir: Path, joined: LocalMap, origin_id: int) -> LocalMap:
    """Write ``poses.txt`` and (with features) ``features.txt`` in the frame of pose ``origin_id``.

    Returns:
        The map in the frame of ``origin_id`` (what was written).
    """
    out_dir.mkdir(parents=True, exist_ok=True)
    in_origin = joined if joined.frame_id == origin_id else change_frame(joined, origin_id)
    write_poses(out_dir / "poses.txt", in_origin, origin_id)
    if (in_origin.kinds == FEATURE).any():
        write_features(out_dir / "features.txt", in_origin)
    return in_origin


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
