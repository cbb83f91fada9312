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

A merge of online divide and conquer not computed yet (:class:`~linear_slam_ros.joining.divide_conquer.Deferred`)
is written as its two inputs and rebuilt as the same merge: writing a state never computes or waits
for a merge. With a :class:`BlobStore` (the node's state directory), every map of at least
:data:`BLOB_MIN_BYTES` is written once, as its own state file named by its checksum
(``blobs/<sha256>.npz``), and referenced by name (``{"__blob__": name}``, listed in the header's
``blobs``): the large levels of the online divide-and-conquer stack do not change between
snapshots, so a snapshot writes only the maps made since the one before. A file written without
a store (``~/save_map``, the CLI's ``--save-state``) holds everything itself.

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
import re
import stat
import weakref
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
import scipy.sparse as sp

from linear_slam_ros.core.durable import fsync_path
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
from linear_slam_ros.joining.hold import HeldClosure
from linear_slam_ros.joining.reinit import Relabels
from linear_slam_ros.joining.sequential import CovarianceMap, SequentialState

logger = logging.getLogger(__name__)

FORMAT_NAME = "linear_slam_ros.state"
FORMAT_VERSION = 8
"""Bumped whenever the tree of a state changes; a file of another version is refused, but for the
versions in :data:`MIGRATED` (2: chains and streams, for islands and several robots; 3: the χ² gate's
variance factor, ``JoinerState.variance``; 4: deferred merges and blob references; 5: the variance
factor's ``tail_confidence`` instead of ``prior_submaps``; 6: the gate's re-initialised features,
``JoinerState.relabels``; 7: forward loop closures held back, ``JoinerState.hold_closures`` and ``held``;
8: the robots' slots, ``JoinerState.robots``)."""

_PRIOR_SUBMAPS_DROPPED = (
    "the χ² gate's tail calibration is an upper confidence bound since version 5: the file's "
    "prior_submaps is not used (the fused NIS are kept)"
)
MIGRATED: dict[int, str | None] = {
    2: "the χ² gate's variance factor starts afresh (version 2 did not keep one)",
    3: _PRIOR_SUBMAPS_DROPPED,
    4: _PRIOR_SUBMAPS_DROPPED,
    5: None,
    6: None,
    7: None,
}
"""Older versions still read, and what reading them changes (``None``: nothing, no warning): a
version 2 tree has no ``JoinerState.variance``, which takes its default
(:class:`~linear_slam_ros.joining.gate.VarianceFactor`, the prior alone); a version 3 or 4
variance factor's ``prior_submaps`` is dropped (:func:`_variance_factor`); everything else is
read exactly. A version 3 tree is a version 4 tree without deferred merges or blobs; a version 5
tree has no ``JoinerState.relabels``, which takes its default (no feature re-initialised: the gate
re-initialised none before version 6); a version 6 tree has no ``JoinerState.hold_closures`` nor
``held``, which take their defaults (nothing held: closures were never held before version 7); a
version 7 tree has no ``JoinerState.robots`` (not recorded: a restore checks the robots' names only)."""

BLOB_MIN_BYTES = 256 << 10
"""Maps of at least this many bytes of arrays are written as blobs when a :class:`BlobStore` is given."""


class SnapshotError(LinearSlamError):
    """A state file cannot be written or read back exactly (missing, truncated, corrupt, other version)."""


def _variance_factor(prior_submaps: int | None = None, **fields: Any) -> VarianceFactor:
    """Rebuild a :class:`VarianceFactor`; the ``prior_submaps`` of versions 3 and 4 is dropped (see :data:`MIGRATED`)."""
    del prior_submaps
    return VarianceFactor(**fields)


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
    "Relabels": Relabels,
    "HeldClosure": HeldClosure,
    "LocalMap": LocalMap.trusted,  # computed by the core: not validated again
}
"""Dataclasses a state file may hold, and how each is rebuilt from its fields."""

CLASSES_BEFORE_5: dict[str, Callable[..., Any]] = {**CLASSES, "VarianceFactor": _variance_factor}
"""How the files of versions 3 and 4 are rebuilt: their variance factor's ``prior_submaps`` is dropped.
A file of the current version that names that field is malformed (refused)."""

ENUMS: dict[str, type[enum.Enum]] = {"JoinMethod": JoinMethod, "MapType": MapType, "OutputFrame": OutputFrame}

CACHE_FIELDS = frozenset({"layout"})
"""Dataclass fields that are caches of other fields: not written, rebuilt on demand."""


# ------------------------------------------------------------------------------------ encoding


def _field(value: Any, name: str, lower_triangle: bool) -> Any:
    """Return a field to write; a matrix kept in its lower triangle gets zeros above it (its upper
    triangle holds whatever the memory held: two identical runs would write different files)."""
    field = getattr(value, name)
    return np.asfortranarray(np.tril(field)) if lower_triangle else field


class _Encoder:
    def __init__(self, blobs: BlobStore | None = None) -> None:
        self.arrays: dict[str, npt.NDArray[Any]] = {}
        self.blobs = blobs
        self.blob_names: list[str] = []

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
        if isinstance(value, Deferred):
            inputs = value.inputs  # read once: a worker may finish the merge meanwhile (then None)
            if inputs is None:
                return self.encode(value.value())
            return {"__deferred__": [self.encode(inputs[0]), self.encode(inputs[1])], "count": value.count}
        if isinstance(value, LocalMap) and self.blobs is not None and value.nbytes >= self.blobs.min_bytes:
            name = self.blobs.put(value)
            self.blob_names.append(name)
            return {"__blob__": name}
        if dataclasses.is_dataclass(value) and not isinstance(value, type):
            name = type(value).__name__
            if name not in CLASSES:
                raise SnapshotError(f"cannot write a {name}: not a class a state file may hold")
            kept = [f.name for f in dataclasses.fields(value) if f.name not in CACHE_FIELDS]
            lower = getattr(type(value), "LOWER_TRIANGLE_FIELDS", ())
            fields = {name_: self.encode(_field(value, name_, name_ in lower)) for name_ in kept}
            return {"__type__": name, "fields": fields}
        raise SnapshotError(f"cannot write a value of type {type(value).__name__} into a state file")


def _checksum(tree_json: bytes, arrays: dict[str, npt.NDArray[Any]]) -> str:
    """SHA-256 of the tree and of every array's key, dtype, shape, memory order and bytes."""
    digest = hashlib.sha256(tree_json)
    for key in sorted(arrays, key=lambda k: int(k[1:])):
        a = arrays[key]
        fortran = bool(a.flags.f_contiguous and not a.flags.c_contiguous)
        digest.update(f"{key}:{a.dtype.str}:{a.shape}:{fortran}".encode())
        contiguous = a if a.flags.c_contiguous or a.flags.f_contiguous else np.ascontiguousarray(a)
        digest.update(contiguous.reshape(-1, order="A").view(np.uint8).data)  # the bytes of tobytes(order="A"), uncopied
    return digest.hexdigest()


def encode_state(state: Any, blobs: BlobStore | None = None, encoder: _Encoder | None = None) -> dict[str, npt.NDArray[Any]]:
    """Return the arrays of a state file (``header`` included) for ``state``.

    Args:
        state: the value to write.
        blobs: where maps of at least :data:`BLOB_MIN_BYTES` go (written there now unless they
            already are); ``None`` keeps everything in the returned arrays.
        encoder: the encoder to use (the caller reads its ``blob_names`` afterwards).

    Raises:
        SnapshotError: the state holds a value a state file cannot hold, or a blob cannot be written.
    """
    enc = encoder if encoder is not None else _Encoder(blobs)
    tree = enc.encode(state)
    tree_json = json.dumps(tree, sort_keys=True, allow_nan=False).encode()
    header = {"format": FORMAT_NAME, "version": FORMAT_VERSION, "tree": tree, "sha256": _checksum(tree_json, enc.arrays),
              "blobs": sorted(set(enc.blob_names))}
    return {"header": np.frombuffer(json.dumps(header).encode(), dtype=np.uint8), **enc.arrays}


def _stage(path: Path, arrays: dict[str, npt.NDArray[Any]]) -> Path:
    """Write a state file's bytes to a temporary file beside ``path`` (not synced); return its path.

    Raises:
        OSError: the file cannot be written.
    """
    tmp = path.with_name(f".{path.name}.tmp")
    path.parent.mkdir(parents=True, exist_ok=True)
    try:
        with open(tmp, "wb") as fh:
            np.savez(fh, allow_pickle=False, **arrays)
    except BaseException:  # a full disk: what was written of it would hold the space the journal needs
        tmp.unlink(missing_ok=True)
        raise
    return tmp


def _commit(tmp: Path, path: Path) -> None:
    """Fsync a staged file and rename it over ``path`` (the folder is synced by the caller).

    Raises:
        OSError: the file cannot be synced or renamed.
    """
    fsync_path(tmp)
    os.replace(tmp, path)


def write_snapshot(path: Path, state: Any, blobs: BlobStore | None = None) -> frozenset[str]:
    """Write ``state`` to ``path`` atomically (temporary file, fsync, rename, fsync of the folder).

    Args:
        path: the state file.
        state: the value to write.
        blobs: with a store, its new blobs are written (and their folder synced) before the state
            file, so a state file on disk never names a blob the disk lacks.

    Returns:
        The names of the blobs the file names (empty without a store).

    Raises:
        SnapshotError: the state cannot be encoded, or the file cannot be written (names the path).
    """
    path = Path(path)
    enc = _Encoder(blobs)
    arrays = encode_state(state, blobs, enc)  # stages the new blobs
    try:
        tmp = _stage(path, arrays)  # every byte is written before the first fsync: one journal commit for most
        if blobs is not None:
            blobs.sync()
        _commit(tmp, path)
        fsync_path(path.parent)
    except OSError as exc:
        raise SnapshotError(f"cannot write state file {path}: {exc}") from None
    return frozenset(enc.blob_names)


class BlobStore:
    """A folder of maps written once each, named by their checksum, shared by the snapshots beside it.

    A map written or read by this store (the same object: states are immutable values) is not
    encoded again. A new blob is staged in a temporary file and made durable by :meth:`sync`
    (fsync, rename, fsync of the folder), so a file named like a blob is always whole.
    :meth:`collect` deletes the blobs no kept snapshot names.

    Attributes:
        folder: where the blobs are (``<name>.npz``).
        min_bytes: maps of fewer bytes of arrays stay in the state file.
    """

    def __init__(self, folder: Path, min_bytes: int = BLOB_MIN_BYTES) -> None:
        self.folder = Path(folder)
        self.min_bytes = min_bytes
        self._written: dict[int, tuple[weakref.ref[LocalMap], str]] = {}
        self._staged: dict[str, Path] = {}  # blob name -> temporary file

    def path(self, name: str) -> Path:
        """Return the file of blob ``name``."""
        return self.folder / f"{name}.npz"

    def put(self, local_map: LocalMap) -> str:
        """Return the name of ``local_map``'s blob, writing it (not yet synced: :meth:`sync`) when new.

        Raises:
            SnapshotError: the blob cannot be written (names the file).
        """
        known = self._written.get(id(local_map))
        if known is not None and known[0]() is local_map and (known[1] in self._staged or self.path(known[1]).exists()):
            return known[1]
        arrays = encode_state(local_map)
        name = json.loads(bytes(arrays["header"]).decode())["sha256"]
        path = self.path(name)
        try:
            self._staged[name] = _stage(path, arrays)
        except OSError as exc:
            raise SnapshotError(f"cannot write blob {path}: {exc}") from None
        self._remember(local_map, name)
        return name

    def _remember(self, local_map: LocalMap, name: str) -> None:
        self._written[id(local_map)] = (weakref.ref(local_map), name)

    def sync(self) -> None:
        """Make the blobs staged since the last call durable: fsync, rename, fsync of the folder.

        Raises:
            OSError: a blob cannot be synced or renamed (then every map is written afresh next time).
        """
        try:
            if self._staged:
                for name, tmp in self._staged.items():
                    _commit(tmp, self.path(name))
                fsync_path(self.folder)
        except OSError:
            self._written.clear()
            raise
        finally:
            self._staged.clear()
        self._written = {k: v for k, v in self._written.items() if v[0]() is not None}

    def read(self, name: Any, where: str) -> Any:
        """Return the map of blob ``name``, checked as a state file is, and against its name.

        Raises:
            SnapshotError: the name is malformed, or the blob is missing, corrupt, or not the one named.
        """
        if not isinstance(name, str) or not _BLOB_NAME.match(name):
            raise SnapshotError(f"state file {where}: malformed blob name {str(name)[:80]!r}")
        path = self.path(name)
        arrays = _read_arrays(path)
        value = decode_state(arrays, str(path))  # checks the header, the version and the checksum
        if json.loads(bytes(arrays["header"]).decode())["sha256"] != name or not isinstance(value, LocalMap):
            raise SnapshotError(f"blob {path} is not the map state file {where} names (the file is corrupt)")
        self._remember(value, name)  # a restored state's levels are not written again
        return value

    def collect(self, keep: set[str]) -> int:
        """Delete the blobs (and left-over temporary files) not named in ``keep``; return how many.

        Raises:
            OSError: the folder cannot be listed.
        """
        removed = 0
        if not self.folder.is_dir():
            return 0
        for p in self.folder.iterdir():
            name = p.name.removesuffix(".npz")
            if p.name.endswith(".tmp") or (p.name.endswith(".npz") and name not in keep):
                p.unlink(missing_ok=True)
                removed += 1
        return removed


_BLOB_NAME = re.compile(r"^[0-9a-f]{64}$")


def blob_names(path: Path) -> set[str]:
    """Return the blobs state file ``path`` names (reads its header only).

    Raises:
        SnapshotError: the file is missing or its header cannot be read.
    """
    try:
        with np.load(path, allow_pickle=False) as npz:
            header = json.loads(bytes(npz["header"]).decode())
    except FileNotFoundError:
        raise SnapshotError(f"state file {path} does not exist") from None
    except SnapshotError:
        raise
    except Exception as exc:  # a trust boundary, as in _read_arrays
        raise SnapshotError(f"state file {path}: header cannot be read ({exc})") from None
    names = header.get("blobs", []) if isinstance(header, dict) else []
    return {n for n in names if isinstance(n, str)}


# ------------------------------------------------------------------------------------ decoding


class _Decoder:
    def __init__(
        self, arrays: dict[str, npt.NDArray[Any]], where: str, blobs: BlobStore | None, version: int = FORMAT_VERSION
    ) -> None:
        self.arrays = arrays
        self.where = where
        self.blobs = blobs
        self.classes = CLASSES_BEFORE_5 if version < 5 else CLASSES

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
        if "__deferred__" in node:
            left, right = (self.decode(v) for v in node["__deferred__"])
            if not all(isinstance(e, LocalMap | Deferred) for e in (left, right)):
                raise SnapshotError(f"state file {self.where}: a deferred merge of something other than maps")
            return Deferred(left, right, int(node["count"]))
        if "__blob__" in node:
            if self.blobs is None:
                raise SnapshotError(f"state file {self.where} names blob {node['__blob__']!r} and has no blob folder")
            return self.blobs.read(node["__blob__"], self.where)
        if "__type__" in node:
            build = self.classes.get(node["__type__"])
            if build is None:
                raise SnapshotError(f"state file {self.where}: class {node['__type__']!r} is not one a state file may hold")
            return build(**{k: self.decode(v) for k, v in node["fields"].items()})
        raise SnapshotError(f"state file {self.where}: unexpected entry {str(node)[:60]!r}")


def decode_state(arrays: dict[str, npt.NDArray[Any]], where: str = "<memory>", blobs: BlobStore | None = None) -> Any:
    """Rebuild a state from the arrays of a state file, checking format, version and checksum.

    Blobs the tree names are read from ``blobs`` (each checked the same way).

    Raises:
        SnapshotError: no header, another format or version, a checksum mismatch, or a malformed
            tree (whatever a hostile file makes the decoding raise is reported as this).
    """
    try:
        return _decode_state(arrays, where, blobs)
    except SnapshotError:
        raise
    except Exception as exc:  # a trust boundary: a crafted tree (NaN, a list for a version, deep nesting...)
        raise SnapshotError(f"state file {where}: malformed state ({type(exc).__name__}: {exc})") from None


def _decode_state(arrays: dict[str, npt.NDArray[Any]], where: str, blobs: BlobStore | None) -> Any:
    if "header" not in arrays:
        raise SnapshotError(f"state file {where}: no header (not a linear_slam_ros state file)")
    try:
        header = json.loads(bytes(arrays["header"]).decode())
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise SnapshotError(f"state file {where}: unreadable header ({exc})") from None
    if not isinstance(header, dict) or header.get("format") != FORMAT_NAME:
        raise SnapshotError(f"state file {where}: not a linear_slam_ros state file")
    version = header.get("version")
    if type(version) is not int or (version != FORMAT_VERSION and version not in MIGRATED):
        raise SnapshotError(
            f"state file {where}: format version {version!r}, this build reads version {FORMAT_VERSION}"
            f" (and {', '.join(str(v) for v in sorted(MIGRATED))})"
        )
    body = {k: v for k, v in arrays.items() if k != "header"}
    tree_json = json.dumps(header.get("tree"), sort_keys=True, allow_nan=False).encode()
    if _checksum(tree_json, body) != header.get("sha256"):
        raise SnapshotError(f"state file {where}: checksum mismatch (the file is corrupt)")
    if version != FORMAT_VERSION and MIGRATED[version] is not None:
        logger.warning("state file %s: format version %s read by this build (version %d): %s", where, version,
                       FORMAT_VERSION, MIGRATED[version])
    return _Decoder(body, where, blobs, version).decode(header["tree"])


def _read_arrays(path: Path) -> dict[str, npt.NDArray[Any]]:
    try:
        if not stat.S_ISREG(path.stat().st_mode):  # a FIFO would block the reader, /dev/zero never end
            raise SnapshotError(f"state file {path} is not a regular file")
        data = path.read_bytes()
        with np.load(io.BytesIO(data), allow_pickle=False) as npz:
            return {k: npz[k] for k in npz.files}
    except FileNotFoundError:
        raise SnapshotError(f"state file {path} does not exist") from None
    except Exception as exc:  # a trust boundary: whatever numpy or zipfile raise on a bad file (zlib.error...)
        raise SnapshotError(f"state file {path} cannot be read (truncated or not a state file: {exc})") from None


def read_snapshot(path: Path, blobs: BlobStore | None = None) -> Any:
    """Read a state written by :func:`write_snapshot`.

    Args:
        path: the state file.
        blobs: the store its blobs are in; ``None``: the folder ``blobs`` beside the file (where
            the node's state directory keeps them).

    Raises:
        SnapshotError: the file (or a blob it names) is missing, truncated, corrupt or of another
            format version (names the file).
    """
    path = Path(path)
    return decode_state(_read_arrays(path), str(path), blobs if blobs is not None else BlobStore(path.parent / "blobs"))
