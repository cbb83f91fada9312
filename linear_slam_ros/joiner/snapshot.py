"""Exact snapshots of the joiner state: one ``.npz`` file, bit for bit, versioned, checksummed, atomic.

The state (:class:`~linear_slam_ros.joiner.joiner.JoinerState`, whatever its strategy) is a tree
of frozen dataclasses, tuples, numbers, strings, enums, numpy arrays and sparse matrices. It is
written as:

- one array entry ``a<k>`` per numpy array (dtype, shape and memory order kept, so a Fortran-
  ordered covariance comes back Fortran-ordered), three per CSR matrix;
- ``header``: UTF-8 JSON (as a ``uint8`` array) with ``format`` (:data:`FORMAT_NAME`),
  ``version`` (:data:`FORMAT_VERSION`), ``tree`` (the state with arrays replaced by their keys,
  dataclasses by ``{"__type__": name, "fields": {...}}``) and ``sha256``: the hash of the tree's
  JSON and of every array's dtype, shape and bytes in key order.

Loading never executes code: ``numpy.load`` with ``allow_pickle=False``, and only the classes in
:data:`CLASSES` are rebuilt (layout caches are left out and rebuilt on demand). A file that is
truncated, fails its checksum or has another format version raises :class:`SnapshotError` naming
the file and the problem (an older version listed in :data:`MIGRATED` is read, with a warning).
:func:`write_snapshot` writes a temporary file, fsyncs it and renames
it over the target, so a reader sees the old file or the new one, never a part.
"""

from __future__ import annotations

import dataclasses
import enum
import hashlib
import io
import json
import logging
import os
import zipfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
import scipy.sparse as sp

from linear_slam_ros.core.errors import LinearSlamError
from linear_slam_ros.core.local_map import LocalMap
from linear_slam_ros.feature_only.maps import FeatureMap
from linear_slam_ros.feature_only.online import FeatureJoinState
from linear_slam_ros.feature_only.precondition import Group
from linear_slam_ros.joiner.config import OutputFrame
from linear_slam_ros.joiner.islands import Chain, Stream
from linear_slam_ros.joiner.joiner import JoinerState, SavedJoiner
from linear_slam_ros.joiner.strategy import JoinMethod, MapType
from linear_slam_ros.joining.divide_conquer import Deferred, OnlineDCState
from linear_slam_ros.joining.gate import VarianceFactor
from linear_slam_ros.joining.sequential import CovarianceMap, SequentialState

logger = logging.getLogger(__name__)

FORMAT_NAME = "linear_slam_ros.state"
FORMAT_VERSION = 3
"""Bumped whenever the tree of a state changes; a file of another version is refused, but for the
versions in :data:`MIGRATED` (2: chains and streams, for islands and several robots; 3: the χ² gate's
variance factor, ``JoinerState.variance``)."""

MIGRATED = {2: "the χ² gate's variance factor starts afresh (version 2 did not keep one)"}
"""Older versions still read, and what reading them changes: a version 2 tree has no
``JoinerState.variance``, which takes its default (:class:`~linear_slam_ros.joining.gate.VarianceFactor`,
the prior alone); everything else is read exactly."""


class SnapshotError(LinearSlamError):
    """A state file cannot be written or read back exactly (missing, truncated, corrupt, other version)."""


CLASSES: dict[str, Callable[..., Any]] = {
    "SavedJoiner": SavedJoiner,
    "JoinerState": JoinerState,
    "Chain": Chain,
    "Stream": Stream,
    "SequentialState": SequentialState,
    "OnlineDCState": OnlineDCState,
    "FeatureJoinState": FeatureJoinState,
    "Group": Group,
    "FeatureMap": FeatureMap,
    "CovarianceMap": CovarianceMap,
    "VarianceFactor": VarianceFactor,
    "LocalMap": LocalMap.trusted,  # computed by the core: not validated again
}
"""Dataclasses a state file may hold, and how each is rebuilt from its fields."""

ENUMS: dict[str, type[enum.Enum]] = {"JoinMethod": JoinMethod, "MapType": MapType, "OutputFrame": OutputFrame}

CACHE_FIELDS = frozenset({"layout"})
"""Dataclass fields that are caches of other fields: not written, rebuilt on demand."""


# ------------------------------------------------------------------------------------ encoding


class _Encoder:
    def __init__(self) -> None:
        self.arrays: dict[str, npt.NDArray[Any]] = {}

    def array(self, value: npt.NDArray[Any]) -> str:
        key = f"a{len(self.arrays)}"
        self.arrays[key] = value
        return key

    def encode(self, value: Any) -> Any:
        if isinstance(value, enum.Enum):  # first: a StrEnum is a str too
            return {"__enum__": type(value).__name__, "value": value.value}
        if value is None or isinstance(value, bool | str):
            return value
        if isinstance(value, int | float):
            return value  # json writes floats with repr: exact
        if isinstance(value, np.integer | np.floating):
            return {"__scalar__": self.array(np.asarray(value))}
        if isinstance(value, np.ndarray):
            return {"__array__": self.array(value)}
        if isinstance(value, sp.csr_matrix | sp.csr_array):
            arrays = [self.array(value.data), self.array(value.indices), self.array(value.indptr)]
            return {"__csr__": arrays, "shape": list(value.shape)}
        if isinstance(value, tuple | list):
            return {"__tuple__": [self.encode(v) for v in value]}
        if isinstance(value, Deferred):  # a join still to compute: written as its result (waits for it)
            return self.encode(value.value())
        if dataclasses.is_dataclass(value) and not isinstance(value, type):
            name = type(value).__name__
            if name not in CLASSES:
                raise SnapshotError(f"cannot write a {name}: not a class a state file may hold")
            kept = [f.name for f in dataclasses.fields(value) if f.name not in CACHE_FIELDS]
            fields = {name_: self.encode(getattr(value, name_)) for name_ in kept}
            return {"__type__": name, "fields": fields}
        raise SnapshotError(f"cannot write a value of type {type(value).__name__} into a state file")


def _checksum(tree_json: bytes, arrays: dict[str, npt.NDArray[Any]]) -> str:
    """SHA-256 of the tree and of every array's key, dtype, shape, memory order and bytes."""
    digest = hashlib.sha256(tree_json)
    for key in sorted(arrays, key=lambda k: int(k[1:])):
        a = arrays[key]
        fortran = bool(a.flags.f_contiguous and not a.flags.c_contiguous)
        digest.update(f"{key}:{a.dtype.str}:{a.shape}:{fortran}".encode())
        digest.update(a.tobytes(order="A"))
    return digest.hexdigest()


def encode_state(state: Any) -> dict[str, npt.NDArray[Any]]:
    """Return the arrays of a state file (``header`` included) for ``state``.

    Raises:
        SnapshotError: the state holds a value a state file cannot hold.
    """
    enc = _Encoder()
    tree = enc.encode(state)
    tree_json = json.dumps(tree, sort_keys=True, allow_nan=False).encode()
    header = {"format": FORMAT_NAME, "version": FORMAT_VERSION, "tree": tree, "sha256": _checksum(tree_json, enc.arrays)}
    return {"header": np.frombuffer(json.dumps(header).encode(), dtype=np.uint8), **enc.arrays}


def write_snapshot(path: Path, state: Any) -> None:
    """Write ``state`` to ``path`` atomically (temporary file, fsync, rename, fsync of the folder).

    Raises:
        SnapshotError: the state cannot be encoded, or the file cannot be written (names the path).
    """
    path = Path(path)
    arrays = encode_state(state)
    tmp = path.with_name(f".{path.name}.tmp")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        with open(tmp, "wb") as fh:
            np.savez(fh, allow_pickle=False, **arrays)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
        dir_fd = os.open(path.parent, os.O_RDONLY)
        try:
            os.fsync(dir_fd)
        finally:
            os.close(dir_fd)
    except OSError as exc:
        raise SnapshotError(f"cannot write state file {path}: {exc}") from None


# ------------------------------------------------------------------------------------ decoding


class _Decoder:
    def __init__(self, arrays: dict[str, npt.NDArray[Any]], where: str) -> None:
        self.arrays = arrays
        self.where = where

    def array(self, key: Any) -> npt.NDArray[Any]:
        if not isinstance(key, str) or key not in self.arrays:
            raise SnapshotError(f"state file {self.where}: missing array {key!r}")
        return self.arrays[key]

    def decode(self, node: Any) -> Any:
        if node is None or isinstance(node, bool | int | float | str):
            return node
        if not isinstance(node, dict):
            raise SnapshotError(f"state file {self.where}: unexpected entry {str(node)[:60]!r}")
        if "__enum__" in node:
            enum_type = ENUMS.get(node["__enum__"])
            if enum_type is None:
                raise SnapshotError(f"state file {self.where}: unknown enum {node['__enum__']!r}")
            return enum_type(node["value"])
        if "__scalar__" in node:
            return self.array(node["__scalar__"])[()]
        if "__array__" in node:
            return self.array(node["__array__"])
        if "__csr__" in node:
            data, indices, indptr = (self.array(k) for k in node["__csr__"])
            return sp.csr_matrix((data, indices, indptr), shape=tuple(node["shape"]))
        if "__tuple__" in node:
            return tuple(self.decode(v) for v in node["__tuple__"])
        if "__type__" in node:
            build = CLASSES.get(node["__type__"])
            if build is None:
                raise SnapshotError(f"state file {self.where}: class {node['__type__']!r} is not one a state file may hold")
            return build(**{k: self.decode(v) for k, v in node["fields"].items()})
        raise SnapshotError(f"state file {self.where}: unexpected entry {str(node)[:60]!r}")


def decode_state(arrays: dict[str, npt.NDArray[Any]], where: str = "<memory>") -> Any:
    """Rebuild a state from the arrays of a state file, checking format, version and checksum.

    Raises:
        SnapshotError: no header, another format or version, a checksum mismatch, or a malformed tree.
    """
    if "header" not in arrays:
        raise SnapshotError(f"state file {where}: no header (not a linear_slam_ros state file)")
    try:
        header = json.loads(bytes(arrays["header"]).decode())
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise SnapshotError(f"state file {where}: unreadable header ({exc})") from None
    if not isinstance(header, dict) or header.get("format") != FORMAT_NAME:
        raise SnapshotError(f"state file {where}: not a linear_slam_ros state file")
    version = header.get("version")
    if version != FORMAT_VERSION and version not in MIGRATED:
        raise SnapshotError(
            f"state file {where}: format version {version!r}, this build reads version {FORMAT_VERSION}"
            f" (and {', '.join(str(v) for v in sorted(MIGRATED))})"
        )
    body = {k: v for k, v in arrays.items() if k != "header"}
    tree_json = json.dumps(header.get("tree"), sort_keys=True, allow_nan=False).encode()
    if _checksum(tree_json, body) != header.get("sha256"):
        raise SnapshotError(f"state file {where}: checksum mismatch (the file is corrupt)")
    if version != FORMAT_VERSION:
        logger.warning("state file %s: format version %s read by this build (version %d): %s", where, version,
                       FORMAT_VERSION, MIGRATED[version])
    try:
        return _Decoder(body, where).decode(header["tree"])
    except (KeyError, TypeError, ValueError) as exc:
        raise SnapshotError(f"state file {where}: malformed state ({type(exc).__name__}: {exc})") from None


def read_snapshot(path: Path) -> Any:
    """Read a state written by :func:`write_snapshot`.

    Raises:
        SnapshotError: the file is missing, truncated, corrupt or of another format version (names the file).
    """
    path = Path(path)
    try:
        data = path.read_bytes()
        with np.load(io.BytesIO(data), allow_pickle=False) as npz:
            arrays = {k: npz[k] for k in npz.files}
    except FileNotFoundError:
        raise SnapshotError(f"state file {path} does not exist") from None
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as exc:
        raise SnapshotError(f"state file {path} cannot be read (truncated or not a state file: {exc})") from None
    return decode_state(arrays, str(path))
