"""Read the benchmark local-map datasets and write results in the reference program's format.

Format (``shared/datasets/README.md``): ``localmap_<i>.txt`` holds ``Ref``, ``n``, ``n`` lines
``<id> <value>`` and the ``n x n`` information matrix. Pose-feature datasets tag pose ``k`` as id
``-k`` and features with ids ``> 0``; pose-only datasets tag pose ``k`` as ``k``.

Synthetic sources: ``read_dataset("synthetic:NAME[@SEED]")`` returns a generated stream (e.g.
``synthetic:city2d-20000``). This layer only knows the name and the cache: generators register
themselves with :func:`register_synthetic` (``linear_slam_ros.evaluation.city`` does when
imported); without one, the stream is read from its cache file (:func:`synthetic_cache_path`,
an ``.npz`` written by :func:`write_dataset_npz`).
"""

from __future__ import annotations

import enum
import logging
import lzma
import os
import re
import shutil
import tarfile
import tempfile
import zlib
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import numpy.typing as npt
import scipy.sparse as sp
from tqdm import tqdm

from linear_slam_ros.core.errors import DatasetError, InvalidMapError
from linear_slam_ros.core.geometry import pose_size
from linear_slam_ros.core.local_map import FEATURE, POSE, LocalMap, default_end_pose, fuse_repeated, var_keys
from linear_slam_ros.core.solvers import DENSE_MAX

logger = logging.getLogger(__name__)

FloatArray = npt.NDArray[np.float64]

_LOCALMAP_RE = re.compile(r"^localmap_(\d+)\.txt$")

PROGRESS_DELAY = 1.0
"""Seconds after which unpacking and reading show a progress bar, on stderr when it is a terminal."""


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
        maps: the local maps in order, ``maps[i]`` read from ``localmap_<seqs[i]>.txt``.
        numbers: the files' numbers when they skip some (lost submaps); empty for ``1..N``.
    """

    name: str
    kind: MapKind
    maps: tuple[LocalMap, ...]
    numbers: tuple[int, ...] = ()

    @property
    def seqs(self) -> tuple[int, ...]:
        """Sequence number of each map: its file's number (``1..N`` without gaps)."""
        return self.numbers if self.numbers else tuple(range(1, len(self.maps) + 1))

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


FILE_SYMMETRY_RTOL = 1e-6
"""How far a local-map file's information may be from symmetric, relative to its largest entry (the benchmark files:
2.1e-9 at most, from their printed digits); the two triangles are averaged below it and refused above."""


def default_cache_dir() -> Path:
    """Return the folder where archives are unpacked (``$LINEAR_SLAM_CACHE`` or ``.cache/datasets``)."""
    return Path(os.environ.get("LINEAR_SLAM_CACHE", Path.cwd() / ".cache" / "datasets"))


def parse_local_map_text(text: str, name: str, source: str | None = None) -> RawLocalMap:
    """Parse the text of one ``localmap_<i>.txt``.

    Args:
        text: the file's text.
        name: the map's name (``localmap_<i>``).
        source: the file, as error messages name it (default ``name``).

    Raises:
        DatasetError: the numbers do not match the format; the message names the file (and
            ``file:line`` for a token that is not a number).
    """
    where = source if source is not None else name
    try:
        nums = np.array(text.split(), dtype=np.float64) if "\t" in text else np.fromstring(text, sep=" ")
    except ValueError:
        raise DatasetError(_garbage_message(text, where)) from None
    raw_name, name = name, where  # messages name the file, the map keeps its name
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
    return RawLocalMap(raw_name, int(ref), pairs[:, 0].astype(np.int64), pairs[:, 1].copy(), info)


def _garbage_message(text: str, where: str) -> str:
    """Return ``where:line: 'token' is not a number`` for the first token of ``text`` float() rejects."""
    for number, line in enumerate(text.splitlines(), start=1):
        for token in line.split():
            try:
                float(token)
            except ValueError:
                return f"{where}:{number}: {token[:40]!r} is not a number"
    return f"{where}: not a list of numbers"


def detect_kind(raw: RawLocalMap) -> MapKind:
    """Detect the map kind from the ids and variable sizes of one parsed map.

    A variable listed twice in a row (parallel edges, as Intel's map 61 lists pose 863) spans twice
    its size, so sizes are read as multiples: 2D when every pose spans a multiple of 3 lines (and
    every feature of 2), 3D when multiples of 6 (and 3). When both fit (every pose spans 6 lines:
    one 3D pose or a 2D pose listed twice), 3D.
    """
    ids = raw.scalar_ids
    starts = np.flatnonzero(np.concatenate([[True], ids[1:] != ids[:-1]]))
    sizes = np.diff(np.concatenate([starts, [ids.size]]))
    group_ids = ids[starts]
    with_features = bool(np.any(group_ids < 0))
    poses = sizes[group_ids <= 0] if with_features else sizes
    features = sizes[group_ids > 0] if with_features else sizes[:0]
    fits = {
        dim: bool(np.all(poses % (3 * (dim - 1)) == 0) and np.all(features % dim == 0)) for dim in (3, 2)
    }
    for dim in (3, 2):  # 3D first: a map of 6-line poses only reads as 3D
        if fits[dim]:
            return {(2, False): MapKind.PG2D, (3, False): MapKind.PG3D, (2, True): MapKind.PF2D, (3, True): MapKind.PF3D}[
                (dim, with_features)
            ]
    if with_features:
        raise DatasetError(
            f"{raw.name}: pose variables span {sorted(set(poses.tolist()))} lines and features "
            f"{sorted(set(features.tolist()))}; expected multiples of 3 and 2 (2D) or of 6 and 3 (3D)"
        )
    raise DatasetError(f"{raw.name}: cannot tell the map kind from variable sizes {sorted(set(sizes.tolist()))}")


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
    skew = np.abs(raw.info - raw.info.T)
    asymmetry = float(skew.max()) if raw.info.size else 0.0
    scale = float(np.abs(raw.info).max()) if raw.info.size else 0.0
    if asymmetry > FILE_SYMMETRY_RTOL * scale:  # the files print ~10 digits: beyond that, not one matrix (one triangle?)
        r, c = (int(k) for k in np.unravel_index(int(np.argmax(skew)), raw.info.shape))
        raise DatasetError(
            f"{raw.name}: the information matrix is not symmetric: entry ({r}, {c}) is {raw.info[r, c]:.10g} "
            f"and ({c}, {r}) {raw.info[c, r]:.10g} (max |I - I^T| {asymmetry:.3g}, above {FILE_SYMMETRY_RTOL:g} "
            "of its largest entry); write the whole matrix, not one triangle"
        )
    values, info = raw.values, 0.5 * (raw.info + raw.info.T)  # the files' last printed digits
    keys = var_keys(var_ids, kinds)
    if np.unique(keys).size != keys.size:
        var_ids, kinds, values, info = fuse_repeated(raw.name, dim, var_ids, kinds, values, info)
    pose_ids = var_ids[kinds == POSE]
    end_id = int(pose_ids.max()) if kind.has_features and pose_ids.size else default_end_pose(frame_id, pose_ids)
    stored: FloatArray | sp.csr_matrix = sp.csr_matrix(info) if info.shape[0] > DENSE_MAX else info
    return LocalMap(dim, frame_id, end_id, var_ids, kinds, values, stored, name=raw.name)


def _archive_identity(archive: Path) -> str:
    """What the unpacked copy's marker records: the archive's path, size and modification time (ns)."""
    st = archive.stat()
    return f"{archive.resolve()}\n{st.st_size}\n{st.st_mtime_ns}\n"


def _unpacked_from(marker: Path, identity: str) -> bool:
    """Whether ``marker`` says its folder is a complete unpack of the archive of ``identity``."""
    try:
        return marker.read_text() == identity
    except OSError:
        return False


def _unpack(archive: Path, cache_dir: Path) -> Path:
    stem = archive.name.removesuffix(".tar.xz").removesuffix(".tar.gz").removesuffix(".tar")
    target = cache_dir / stem
    marker = target / ".complete"
    identity = _archive_identity(archive)
    if _unpacked_from(marker, identity):  # another archive of that name (or this one changed) is unpacked again
        return target
    cache_dir.mkdir(parents=True, exist_ok=True)
    logger.debug("unpacking %s into %s", archive, cache_dir)
    # into a scratch folder first: a truncated archive leaves nothing half-unpacked behind
    scratch = Path(tempfile.mkdtemp(prefix=f".{stem}.", dir=cache_dir))
    try:
        with tarfile.open(archive) as tar, tqdm(desc=f"unpacking {archive.name}", unit="file", disable=None,
                                                delay=PROGRESS_DELAY, leave=False) as bar:
            for member in tar:
                tar.extract(member, scratch, filter="data")
                bar.update()
            # read on to the end of the compressed stream: its checksum (xz, gzip) is verified only
            # there, and damage that still decompresses would otherwise unpack as garbage maps
            while tar.fileobj is not None and tar.fileobj.read(1 << 20):
                pass
        if not (scratch / stem).is_dir():
            raise DatasetError(f"{archive} did not unpack to a folder named {stem!r}")
        (scratch / stem / marker.name).write_text(identity)  # complete before it takes the target's name
        _move_into_place(scratch / stem, target, marker, identity)
    except (tarfile.TarError, OSError, EOFError, lzma.LZMAError, zlib.error) as exc:
        if isinstance(exc, EOFError):
            reason = "the archive is truncated"
        elif isinstance(exc, tarfile.ReadError):
            reason = "not a tar archive, or a truncated or corrupt one"
        else:
            reason = " ".join(str(exc).split()) or type(exc).__name__
        raise DatasetError(f"cannot unpack {archive}: {reason}") from None
    finally:
        shutil.rmtree(scratch, ignore_errors=True)
    return target


def _move_into_place(unpacked: Path, target: Path, marker: Path, identity: str) -> None:
    """Rename a complete unpacked folder to ``target``, unless another process put a complete one of the same
    archive there first.

    Two processes may unpack one archive at once (the test workers, two CLI runs): the rename
    never replaces a folder another process may be reading. A ``target`` whose ``marker`` does not
    name this archive (an unpack that did not finish, another archive of that name, this one since
    changed) is removed first.
    """
    for _ in range(3):
        try:
            unpacked.rename(target)
            return
        except OSError:  # the target exists (rename does not replace a non-empty folder)
            if _unpacked_from(marker, identity):
                return  # another process's complete unpack: ours is dropped with the scratch folder
            shutil.rmtree(target, ignore_errors=True)
    unpacked.rename(target)

def resolve_dataset_dir(path: str | Path, cache_dir: Path | None = None) -> Path:
    """Return the folder of ``localmap_<i>.txt`` files for a folder or a ``.tar.xz`` archive."""
    p = Path(path)
    if p.is_dir():
        return p
    if p.is_file() and ".tar" in p.name:
        return _unpack(p, cache_dir or default_cache_dir())
    raise DatasetError(f"dataset {str(p)!r} is neither a folder nor a .tar.xz archive")


def list_local_map_files(folder: Path) -> list[Path]:
    """Return ``localmap_<i>.txt`` files of a folder sorted by ``i``.

    Numbers may skip some (a lost submap): the maps are joined in the order of their numbers and
    the gap is handled as islands (:mod:`~linear_slam_ros.joiner.islands`); one warning lists the
    missing numbers.
    """
    found = []
    for entry in folder.iterdir():
        m = _LOCALMAP_RE.match(entry.name)
        if m:
            found.append((int(m.group(1)), entry))
    if not found:
        if (folder / "metadata.yaml").is_file():  # bags are read with rosbags, outside this layer
            raise DatasetError(
                f"{folder} is a rosbag2 bag, not a dataset folder: the CLI and the bag tools read it "
                "(msg_adapters.bags.read_bag_submaps)"
            )
        raise DatasetError(f"{folder}: no localmap_<i>.txt files")
    found.sort()
    for (a, file_a), (b, file_b) in zip(found, found[1:], strict=False):
        if a == b:  # localmap_2.txt and localmap_02.txt: both were joined, as two submaps
            raise DatasetError(f"{folder}: {file_a.name} and {file_b.name} both have number {a}")
    numbers = local_map_numbers([f for _, f in found])
    if numbers[0] < 1:
        raise DatasetError(f"{folder}: local map numbers start at 1 (found localmap_{numbers[0]}.txt)")
    if numbers[-1] != len(numbers):
        missing = sorted(set(range(1, numbers[-1] + 1)) - set(numbers))
        logger.warning(
            "%s: %d local map(s) missing (numbers %s%s): the maps are joined in the order of their numbers, "
            "the gaps as islands", folder, len(missing), missing[:5], "..." if len(missing) > 5 else "",
        )
    return [f for _, f in found]


def local_map_numbers(files: Sequence[Path]) -> tuple[int, ...]:
    """Return the number ``i`` of each ``localmap_<i>.txt`` file."""
    out = []
    for f in files:
        m = _LOCALMAP_RE.match(f.name)
        if m is None:
            raise DatasetError(f"{f} is not named localmap_<i>.txt")
        out.append(int(m.group(1)))
    return tuple(out)


def read_dataset(path: str | Path, kind: MapKind | str | None = None, cache_dir: Path | None = None) -> Dataset:
    """Read a dataset from a folder or archive, or a synthetic stream.

    Args:
        path: folder of ``localmap_<i>.txt``, a ``.tar.xz`` archive (unpacked into ``cache_dir``),
            or ``synthetic:NAME[@SEED]`` (:func:`read_synthetic`).
        kind: map kind; detected from the first map's ids when ``None`` (a synthetic stream
            has its own kind, which ``kind`` must match).
        cache_dir: where archives are unpacked and synthetic streams cached (default
            :func:`default_cache_dir`).

    Raises:
        DatasetError: unreadable or malformed files, an unknown or ungenerated synthetic stream.
        InvalidMapError: a map breaks an invariant.
    """
    if str(path).startswith(SYNTHETIC_PREFIX):
        dataset = read_synthetic(str(path), cache_dir)
        if kind is not None and MapKind(kind) != dataset.kind:
            raise DatasetError(f"{path} is a {dataset.kind.value} stream, not {MapKind(kind).value}")
        return dataset
    folder = resolve_dataset_dir(path, cache_dir)
    files = list_local_map_files(folder)
    name = Path(path).name.removesuffix(".tar.xz")
    map_kind = MapKind(kind) if kind is not None else None
    maps = []
    # a bar on a terminal (stderr) when reading takes over PROGRESS_DELAY s, as for VicPark_6898 (7 s)
    with tqdm(total=len(files), desc=f"reading {name}", unit="map", disable=None, delay=PROGRESS_DELAY, leave=False) as bar:
        for f in files:
            try:
                text = f.read_text(encoding="utf-8-sig")  # a byte-order mark (an editor's) is not a number
            except (OSError, UnicodeDecodeError) as exc:
                raise DatasetError(f"cannot read {f}: {exc}") from None
            raw = parse_local_map_text(text, f.stem, source=str(f))
            if map_kind is None:
                map_kind, detected_from = detect_kind(raw), raw.name
            try:
                maps.append(to_local_map(raw, map_kind))
            except DatasetError as exc:  # messages name the file (with several datasets, which folder)
                message = str(exc)
                message = str(f) + message[len(raw.name):] if message.startswith(f"{raw.name}:") else f"{f}: {message}"
                if kind is not None:
                    raise DatasetError(message) from None
                hint = f"kind {map_kind.value} detected from {detected_from}: give the kind if it is another"
                raise DatasetError(f"{message} ({hint})") from None
            except InvalidMapError as exc:
                raise InvalidMapError(f"{f}: {exc}") from None
            bar.update()
    assert map_kind is not None  # list_local_map_files returns at least one file
    numbers = local_map_numbers(files)
    return Dataset(name, map_kind, tuple(maps), numbers if numbers[-1] != len(numbers) else ())


# ---------------------------------------------------------------------------- synthetic sources

SYNTHETIC_PREFIX = "synthetic:"
"""Prefix of a synthetic stream's name where a dataset path is expected."""

SyntheticSource = Callable[[str, int, "Path | None"], Dataset]
"""A generator: ``(name, seed, cache_dir) -> Dataset`` (it may read and write the cache)."""

_SYNTHETIC_SOURCES: dict[str, SyntheticSource] = {}


def register_synthetic(family: str, source: SyntheticSource) -> None:
    """Make ``synthetic:<family>-<size>[@seed]`` readable by :func:`read_dataset` through ``source``.

    Called by the generators' module (a higher layer) when it is imported.
    """
    _SYNTHETIC_SOURCES[family] = source


def parse_synthetic_name(spec: str) -> tuple[str, int]:
    """Return ``(name, seed)`` of ``[synthetic:]NAME[@SEED]`` (seed 0 when not given).

    Raises:
        DatasetError: an empty name or a seed that is not a non-negative integer.
    """
    body = spec.removeprefix(SYNTHETIC_PREFIX)
    name, _, seed = body.partition("@")
    if not name or (seed and not seed.isdigit()):
        raise DatasetError(f"malformed synthetic stream {spec!r}: expected {SYNTHETIC_PREFIX}NAME[@SEED], e.g. city2d-20000@1")
    return name, int(seed or 0)


def synthetic_cache_path(name: str, seed: int, cache_dir: Path | None = None) -> Path:
    """Return the cache file of synthetic stream ``name`` with ``seed``: ``<cache>/synthetic/<name>-seed<seed>.npz``."""
    return (cache_dir or default_cache_dir()) / "synthetic" / f"{name}-seed{seed}.npz"


def read_synthetic(spec: str, cache_dir: Path | None = None) -> Dataset:
    """Return the synthetic stream ``[synthetic:]NAME[@SEED]``: generated (or cached) by its
    registered source, else read from its cache file.

    Raises:
        DatasetError: malformed name, no registered source and no cache file.
    """
    name, seed = parse_synthetic_name(spec)
    source = _SYNTHETIC_SOURCES.get(name.rpartition("-")[0])
    if source is not None:
        return source(name, seed, cache_dir)
    path = synthetic_cache_path(name, seed, cache_dir)
    if not path.is_file():
        raise DatasetError(
            f"synthetic stream {name!r} (seed {seed}) is not generated: no {path}. Run "
            f"'python -m linear_slam_ros.evaluation.city {name} --seed {seed}' or 'make bags' first"
        )
    return read_dataset_npz(path)[0]


def write_dataset_npz(path: Path, dataset: Dataset, extra: Mapping[str, npt.NDArray[np.generic]] | None = None) -> None:
    """Write a dataset (and ``extra`` arrays) to one ``.npz`` file, atomically (temporary file, rename).

    Per map: frame and end pose, variable ids and kinds, state and the upper triangle of the
    information (row-major), all concatenated; ``extra`` names must not start with ``maps_``.
    """
    maps = dataset.maps
    uppers = [m.info_dense()[np.triu_indices(m.x.size)] for m in maps]
    arrays: dict[str, npt.NDArray[np.generic]] = {
        "maps_name": np.array(dataset.name),
        "maps_kind": np.array(dataset.kind.value),
        "maps_frame": np.array([m.frame_id for m in maps], np.int64),
        "maps_end": np.array([-1 if m.end_id is None else m.end_id for m in maps], np.int64),
        "maps_n_vars": np.array([m.n_vars for m in maps], np.int64),
        "maps_ids": np.concatenate([m.ids for m in maps]) if maps else np.zeros(0, np.int64),
        "maps_kinds": np.concatenate([m.kinds for m in maps]) if maps else np.zeros(0, np.int8),
        "maps_x": np.concatenate([m.x for m in maps]) if maps else np.zeros(0),
        "maps_info_upper": np.concatenate(uppers) if uppers else np.zeros(0),
        **(extra or {}),
    }
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp.npz")
    np.savez(tmp, **arrays)  # type: ignore[arg-type]
    os.replace(tmp, path)


def read_dataset_npz(path: Path) -> tuple[Dataset, dict[str, npt.NDArray[np.generic]]]:
    """Read a dataset written by :func:`write_dataset_npz`; return it and the extra arrays.

    Every map is validated as when read from text.

    Raises:
        DatasetError: unreadable file or inconsistent sizes.
        InvalidMapError: a map breaks an invariant.
    """
    try:
        with np.load(path, allow_pickle=False) as data:
            arrays = {k: data[k] for k in data.files}
    except (OSError, ValueError) as exc:
        raise DatasetError(f"cannot read {path}: {exc}") from None
    try:
        kind = MapKind(str(arrays["maps_kind"]))
        n_vars, ids, kinds = arrays["maps_n_vars"], arrays["maps_ids"], arrays["maps_kinds"].astype(np.int8)
        x, upper = arrays["maps_x"], arrays["maps_info_upper"]
        frames, ends = arrays["maps_frame"], arrays["maps_end"]
        name = str(arrays["maps_name"])
    except (KeyError, ValueError) as exc:
        raise DatasetError(f"{path}: not a dataset file ({exc})") from None
    dim = kind.dim
    maps = []
    v = s = u = 0
    for i, nv in enumerate(n_vars.tolist()):
        k = kinds[v : v + nv]
        n = int(np.where(k == POSE, pose_size(dim), dim).sum())
        tri = n * (n + 1) // 2
        if v + nv > ids.size or s + n > x.size or u + tri > upper.size:
            raise DatasetError(f"{path}: map {i + 1} runs past the end of the arrays")
        info = np.zeros((n, n))
        info[np.triu_indices(n)] = upper[u : u + tri]
        info = info + np.triu(info, 1).T
        end: int | None = int(ends[i]) if int(ends[i]) >= 0 else None
        maps.append(LocalMap(dim, int(frames[i]), end, ids[v : v + nv], k, x[s : s + n], info, name=f"{name}_{i + 1}"))
        v, s, u = v + nv, s + n, u + tri
    extra = {key: value for key, value in arrays.items() if not key.startswith("maps_")}
    return Dataset(name, kind, tuple(maps)), extra


def check_origin_frame(local_map: LocalMap, origin_id: int) -> None:
    """Raise :class:`InvalidMapError` unless ``local_map`` is in the frame of pose ``origin_id`` (what pose writers need)."""
    if local_map.frame_id != origin_id:
        raise InvalidMapError(
            f"poses must be written in the frame of pose {origin_id}, map {local_map.name!r} is in {local_map.frame_id}"
        )


def write_poses(path: Path, local_map: LocalMap, origin_id: int = 0) -> None:
    """Write ``k x y phi`` / ``k x y z alpha beta gamma`` lines for every pose, sorted by ``k``.

    The map must be in the frame of pose ``origin_id``, which is written as the origin.

    Raises:
        InvalidMapError: the map is not in the frame of ``origin_id``.
    """
    check_origin_frame(local_map, origin_id)
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
    "read_synthetic",
    "register_synthetic",
    "write_poses",
    "write_features",
]
