"""Read the benchmark local-map datasets and write results in the reference program's format.

Format (``shared/datasets/README.md``): ``localmap_<i>.txt`` holds ``Ref``, ``n``, ``n`` lines
``<id> <value>`` and the ``n x n`` information matrix. Pose-feature datasets tag pose ``k`` as id
``-k`` and features with ids ``> 0``; pose-only datasets tag pose ``k`` as ``k``.
"""

from __future__ import annotations

import enum
import logging
import os
import re
import tarfile
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import numpy.typing as npt
import scipy.sparse as sp

from linear_slam_ros.core.errors import DatasetError, InvalidMapError
from linear_slam_ros.core.geometry import pose_size
from linear_slam_ros.core.local_map import FEATURE, POSE, LocalMap, default_end_pose, fuse_repeated, var_keys
from linear_slam_ros.core.solvers import DENSE_MAX

logger = logging.getLogger(__name__)

FloatArray = npt.NDArray[np.float64]

_LOCALMAP_RE = re.compile(r"^localmap_(\d+)\.txt$")


class MapKind(str, enum.Enum):  # noqa: UP042 - enum.StrEnum would change str() and format() of the members
    """The kind of a dataset's local maps: dimension and pose-feature (PF) or pose-only (PG)."""

    PF2D = "2DPF"
    PF3D = "3DPF"
    PG2D = "2DPG"
    PG3D = "3DPG"

    @property
    def dim(self) -> int:
        """2 or 3."""
        return 2 if self.value.startswith("2") else 3

    @property
    def has_features(self) -> bool:
        """Whether the maps hold point features (pose-feature kind)."""
        return self.value.endswith("PF")


@dataclass(frozen=True)
class Dataset:
    """A sequence of local maps to be joined in order.

    Attributes:
        name: folder or archive stem, e.g. ``"VicPark_200_local_maps"``.
        kind: detected or given map kind.
        maps: the local maps, ``maps[i]`` read from ``localmap_<i + 1>.txt``.
    """

    name: str
    kind: MapKind
    maps: tuple[LocalMap, ...]

    @property
    def dim(self) -> int:
        """2 or 3."""
        return self.kind.dim


@dataclass(frozen=True)
class RawLocalMap:
    """One parsed file before interpretation: reference id, scalar ids, values and information."""

    name: str
    ref: int
    scalar_ids: npt.NDArray[np.int64]
    values: FloatArray
    info: FloatArray


def default_cache_dir() -> Path:
    """Return the folder where archives are unpacked (``$LINEAR_SLAM_CACHE`` or ``.cache/datasets``)."""
    return Path(os.environ.get("LINEAR_SLAM_CACHE", Path.cwd() / ".cache" / "datasets"))


def parse_local_map_text(text: str, name: str) -> RawLocalMap:
    """Parse the text of one ``localmap_<i>.txt``.

    Raises:
        DatasetError: the numbers do not match the format; the message names the file.
    """
    nums = np.array(text.split(), dtype=np.float64) if "\t" in text else np.fromstring(text, sep=" ")
    if nums.size < 2:
        raise DatasetError(f"{name}: expected 'Ref' and 'n' at the top, found {nums.size} numbers")
    ref, n_f = nums[0], nums[1]
    if ref != int(ref) or n_f != int(n_f) or n_f < 1:
        raise DatasetError(f"{name}: 'Ref' and 'n' must be integers with n >= 1, got {float(ref):g} and {float(n_f):g}")
    n = int(n_f)
    expected = 2 + 2 * n + n * n
    if nums.size != expected:
        raise DatasetError(f"{name}: n = {n} needs {expected} numbers (2 + 2n + n^2), found {nums.size}")
    pairs = nums[2 : 2 + 2 * n].reshape(n, 2)
    if np.any(pairs[:, 0] != np.round(pairs[:, 0])):
        raise DatasetError(f"{name}: variable ids must be integers")
    info = nums[2 + 2 * n :].reshape(n, n)
    return RawLocalMap(name, int(ref), pairs[:, 0].astype(np.int64), pairs[:, 1].copy(), info)


def detect_kind(raw: RawLocalMap) -> MapKind:
    """Detect the map kind from the ids and variable sizes of one parsed map."""
    ids = raw.scalar_ids
    starts = np.flatnonzero(np.concatenate([[True], ids[1:] != ids[:-1]]))
    sizes = np.diff(np.concatenate([starts, [ids.size]]))
    group_ids = ids[starts]
    if np.any(group_ids < 0):
        pose_sizes = set(sizes[group_ids <= 0].tolist())
        if pose_sizes == {3}:
            return MapKind.PF2D
        if pose_sizes == {6}:
            return MapKind.PF3D
        raise DatasetError(f"{raw.name}: pose variables span {sorted(pose_sizes)} lines; expected 3 (2D) or 6 (3D)")
    all_sizes = set(sizes.tolist())
    if all_sizes == {3}:
        return MapKind.PG2D
    if all_sizes == {6}:
        return MapKind.PG3D
    raise DatasetError(f"{raw.name}: cannot tell the map kind from variable sizes {sorted(all_sizes)}")


def to_local_map(raw: RawLocalMap, kind: MapKind) -> LocalMap:
    """Interpret a parsed file as a :class:`LocalMap` of the given kind (validated).

    Raises:
        DatasetError: variable sizes do not fit the kind.
        InvalidMapError: the map breaks an invariant (not SPD, duplicate ids, ...).
    """
    dim = kind.dim
    ids = raw.scalar_ids
    starts = np.flatnonzero(np.concatenate([[True], ids[1:] != ids[:-1]]))
    sizes = np.diff(np.concatenate([starts, [ids.size]]))
    group_ids = ids[starts]
    if kind.has_features:
        kinds = np.where(group_ids <= 0, POSE, FEATURE).astype(np.int8)
        var_ids = np.where(group_ids <= 0, -group_ids, group_ids)
        frame_id = raw.ref
    else:
        kinds = np.full(group_ids.shape, POSE, dtype=np.int8)
        var_ids = group_ids
        frame_id = raw.ref
    expected = np.where(kinds == POSE, pose_size(dim), dim)
    repeats = np.where(sizes % expected == 0, sizes // expected, 1)
    if np.any(repeats > 1):  # the same variable listed twice in a row (parallel edges)
        var_ids, kinds = np.repeat(var_ids, repeats), np.repeat(kinds, repeats)
        group_ids = np.repeat(group_ids, repeats)
        sizes = np.repeat(np.where(repeats > 1, expected, sizes), repeats)
        expected = np.repeat(expected, repeats)
    bad = np.flatnonzero(sizes != expected)
    if bad.size:
        i = int(bad[0])
        raise DatasetError(
            f"{raw.name}: variable {int(group_ids[i])} spans {int(sizes[i])} lines, a {kind.value} "
            f"{'pose' if kinds[i] == POSE else 'feature'} needs {int(expected[i])}"
        )
    values, info = raw.values, 0.5 * (raw.info + raw.info.T)
    keys = var_keys(var_ids, kinds)
    if np.unique(keys).size != keys.size:
        var_ids, kinds, values, info = fuse_repeated(raw.name, dim, var_ids, kinds, values, info)
    pose_ids = var_ids[kinds == POSE]
    end_id = int(pose_ids.max()) if kind.has_features and pose_ids.size else default_end_pose(frame_id, pose_ids)
    stored: FloatArray | sp.csr_matrix = sp.csr_matrix(info) if info.shape[0] > DENSE_MAX else info
    return LocalMap(dim, frame_id, end_id, var_ids, kinds, values, stored, name=raw.name)


def _unpack(archive: Path, cache_dir: Path) -> Path:
    stem = archive.name.removesuffix(".tar.xz").removesuffix(".tar.gz").removesuffix(".tar")
    target = cache_dir / stem
    marker = target / ".complete"
    if marker.exists():
        return target
    cache_dir.mkdir(parents=True, exist_ok=True)
    logger.info("unpacking %s into %s", archive, cache_dir)
    try:
        with tarfile.open(archive) as tar:
            tar.extractall(cache_dir, filter="data")
    except (tarfile.TarError, OSError) as exc:
        raise DatasetError(f"cannot unpack {archive}: {exc}") from None
    if not target.is_dir():
        raise DatasetError(f"{archive} did not unpack to a folder named {stem!r}")
    marker.touch()
    return target


def resolve_dataset_dir(path: str | Path, cache_dir: Path | None = None) -> Path:
    """Return the folder of ``localmap_<i>.txt`` files for a folder or a ``.tar.xz`` archive."""
    p = Path(path)
    if p.is_dir():
        return p
    if p.is_file() and ".tar" in p.name:
        return _unpack(p, cache_dir or default_cache_dir())
    raise DatasetError(f"dataset {str(p)!r} is neither a folder nor a .tar.xz archive")


def list_local_map_files(folder: Path) -> list[Path]:
    """Return ``localmap_<i>.txt`` files of a folder sorted by ``i``, checking ``i`` runs 1..N."""
    found = []
    for entry in folder.iterdir():
        m = _LOCALMAP_RE.match(entry.name)
        if m:
            found.append((int(m.group(1)), entry))
    if not found:
        raise DatasetError(f"{folder}: no localmap_<i>.txt files")
    found.sort()
    numbers = [i for i, _ in found]
    if numbers != list(range(1, len(numbers) + 1)):
        missing = sorted(set(range(1, numbers[-1] + 1)) - set(numbers))
        raise DatasetError(f"{folder}: local maps are not numbered 1..N (missing {missing[:5]})")
    return [f for _, f in found]


def read_dataset(path: str | Path, kind: MapKind | str | None = None, cache_dir: Path | None = None) -> Dataset:
    """Read a dataset from a folder or archive.

    Args:
        path: folder of ``localmap_<i>.txt`` or a ``.tar.xz`` archive (unpacked into ``cache_dir``).
        kind: map kind; detected from the first map's ids when ``None``.
        cache_dir: where archives are unpacked (default :func:`default_cache_dir`).

    Raises:
        DatasetError: unreadable or malformed files.
        InvalidMapError: a map breaks an invariant.
    """
    folder = resolve_dataset_dir(path, cache_dir)
    files = list_local_map_files(folder)
    raws = []
    for f in files:
        try:
            text = f.read_text()
        except OSError as exc:
            raise DatasetError(f"cannot read {f}: {exc}") from None
        raws.append(parse_local_map_text(text, f.stem))
    map_kind = MapKind(kind) if kind is not None else detect_kind(raws[0])
    maps = tuple(to_local_map(r, map_kind) for r in raws)
    name = Path(path).name.removesuffix(".tar.xz")
    return Dataset(name, map_kind, maps)


def write_poses(path: Path, local_map: LocalMap, origin_id: int = 0) -> None:
    """Write ``k x y phi`` / ``k x y z alpha beta gamma`` lines for every pose, sorted by ``k``.

    The map must be in the frame of pose ``origin_id``, which is written as the origin.

    Raises:
        InvalidMapError: the map is not in the frame of ``origin_id``.
    """
    if local_map.frame_id != origin_id:
        raise InvalidMapError(
            f"poses must be written in the frame of pose {origin_id}, map {local_map.name!r} is in {local_map.frame_id}"
        )
    rows = [(origin_id, np.zeros(pose_size(local_map.dim)))]
    for i in np.flatnonzero(local_map.kinds == POSE).tolist():
        rows.append((int(local_map.ids[i]), local_map.x[local_map.scalar_slice(i)]))
    rows.sort(key=lambda r: r[0])
    _write_rows(path, rows)


def write_features(path: Path, local_map: LocalMap) -> None:
    """Write ``id x y [z]`` lines for every feature, sorted by id."""
    rows = [
        (int(local_map.ids[i]), local_map.x[local_map.scalar_slice(i)])
        for i in np.flatnonzero(local_map.kinds == FEATURE).tolist()
    ]
    rows.sort(key=lambda r: r[0])
    _write_rows(path, rows)


def _write_rows(path: Path, rows: Iterable[tuple[int, FloatArray]]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "w") as fh:
        for k, vals in rows:
            fh.write(f"{k} " + " ".join(f"{v:.17g}" for v in vals) + "\n")


__all__ = [
    "Dataset",
    "MapKind",
    "InvalidMapError",
    "read_dataset",
    "write_poses",
    "write_features",
]
