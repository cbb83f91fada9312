"""The documented array layouts of linear_slam_ros messages, independent of any ROS library.

Every message is a ``std_msgs/Float64MultiArray`` whose ``layout.dim`` lists named segments
of ``data``, in order: ``dim[k].label`` is the segment name, ``dim[k].size`` its number of
float64 values and ``dim[k].stride`` equals ``size``. ``layout.data_offset`` is 0. Decoders
find segments by label (unknown labels are skipped, so segments can be added without breaking
old readers) and check every size. Integers are stored as float64 (exact below 2**53).

Local map and global map (``MAP_KIND_*``)::

    header      [version=1, dim, map_kind, seq, stamp_sec, stamp_nanosec, frame_pose_id,
                 end_pose_id (-1: none), n_submaps]
    var_ids     m variable ids
    var_kinds   m kinds: 0 pose, 1 point feature
    state       n values: each pose x y phi (2D) / x y z alpha beta gamma (3D), each feature
                x y [z]; metres, radians; in the frame of pose frame_pose_id
    info_rows   k row indices   \\  the information matrix's upper triangle (i <= j) as sparse
    info_cols   k column indices >  triplets: exact, symmetric by construction, and sized by
    info_vals   k values        /   its non-zeros (a joined map's is sparse; a dense triangle
                                    of VicPark6898's 21292-scalar map would be 1.8 GB)
    stats       (global map only) [n_joined, n_rejected, last_join_ms, join_ms_p50,
                 join_ms_p99, join_ms_max, join_seconds_total, n_islands]
    islands     (global map only) submaps in each island: the main island (the one this
                map is) first, then the others, largest first (README, "Islands")

Feature-only map (the global map of ``map_type: feature-only``): the same segments, with
``frame_pose_id = end_pose_id = -1``, every variable a feature, and one more segment::

    frame_features  the ids of F_O, F_X (2D) or F_O, F_X, F_Y (3D): the features that define
                    the frame (F_O at the origin, F_X on the +x axis, F_Y in the x-y plane with
                    y > 0); they are not in var_ids
    state           first the frame features' free coordinates (2D: x of F_X; 3D: x of F_X,
                    x y of F_Y), then x y [z] of each feature in var_ids; metres

Pose-graph chunk (the relative-pose constraints of one submap)::

    header      [version=1, dim, MAP_KIND_POSE_GRAPH, seq, stamp_sec, stamp_nanosec, n_edges]
    edge_from   k pose ids
    edge_to     k pose ids
    measurement k * p values: pose ``to`` seen from pose ``from`` (p = 3 in 2D, 6 in 3D)
    information k * p * p values: each edge's p x p information, row-major

Input limits (:class:`linear_slam_ros.core.limits.InputLimits`, an optional ``limits`` argument
of every decoder; the default limits when None): the state size, the number of information
triplets and of chunk edges are checked from the header and the declared segment sizes, before
any array is built from them; the numbers (information magnitudes and conditioning, angles,
coordinates) by the validation of the decoded map or graph, with the same limits.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt
import scipy.sparse as sp

from linear_slam_ros.core.errors import InvalidMapError, MessageError
from linear_slam_ros.core.geometry import pose_size
from linear_slam_ros.core.limits import InputLimits, beyond_message, first_beyond, limits_or_default, size_fault
from linear_slam_ros.core.local_map import InfoMatrix, LocalMap, check_information, to_csr
from linear_slam_ros.core.solvers import DENSE_MAX
from linear_slam_ros.feature_only.maps import FeatureMap
from linear_slam_ros.pose_graph.graph import PoseGraph

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]

FORMAT_VERSION = 1
MAP_KIND_LOCAL = 0
"""A front-end's local map (pose-feature, pose-only or feature-only by its variables)."""
MAP_KIND_GLOBAL = 1
"""The joined global map published by the node."""
MAP_KIND_POSE_GRAPH = 2
"""A pose-graph chunk."""

MAP_SEGMENTS = ("header", "var_ids", "var_kinds", "state", "info_rows", "info_cols", "info_vals")
CHUNK_SEGMENTS = ("header", "edge_from", "edge_to", "measurement", "information")
_MAP_READ = frozenset((*MAP_SEGMENTS, "stats", "islands", "frame_features"))
"""Segments of a map message the decoders read (others are ignored, non-finite values included)."""
STATS_FIELDS = (
    "n_joined", "n_rejected", "last_join_ms", "join_ms_p50", "join_ms_p99", "join_ms_max", "join_seconds_total", "n_islands",
)
STATS_FIELDS_V1 = 7
"""Fields of the stats segment before ``n_islands``: a shorter segment is read as far as it goes."""
_MAP_HEADER = 9
_CHUNK_HEADER = 7
_MAX_EXACT = 2.0**53


@dataclass(frozen=True, eq=False)
class Encoded:
    """A message's content: segment labels and one array per segment.

    The message's ``data`` is the segments' concatenation as float64. Each part keeps the dtype
    it was made with (a map's information triplets keep their int32 indices) until it is written
    into a message, so a serialiser that writes the parts one by one
    (:func:`msg_adapters.cdr.to_cdr`) never holds the concatenation beside the message.

    Attributes:
        labels: the segments' labels, in order.
        parts: one 1-D array per segment, of a real dtype whose values float64 holds exactly.
    """

    labels: tuple[str, ...]
    parts: tuple[npt.NDArray[Any], ...]

    def __post_init__(self) -> None:
        if len(self.labels) != len(self.parts):
            raise MessageError(f"Encoded: {len(self.labels)} labels for {len(self.parts)} parts")
        bad = [k for k, part in zip(self.labels, self.parts, strict=True) if np.ndim(part) != 1]
        if bad:
            raise MessageError(f"Encoded: segment(s) {bad} are not 1-D arrays")

    @classmethod
    def of(cls, labels: Sequence[str], sizes: Sequence[int], data: npt.ArrayLike) -> Encoded:
        """Return the content whose concatenated ``data`` is split into segments of ``sizes``.

        Raises:
            MessageError: the sizes do not add up to the data's length.
        """
        flat = np.asarray(data, dtype=np.float64).ravel()
        if sum(sizes) != flat.size:
            raise MessageError(f"Encoded: sizes {list(sizes)} add up to {sum(sizes)} values but data has {flat.size}")
        ends = np.cumsum([0, *sizes])
        return cls(tuple(labels), tuple(flat[a:b] for a, b in zip(ends[:-1], ends[1:], strict=True)))

    @property
    def sizes(self) -> tuple[int, ...]:
        """Each segment's number of values."""
        return tuple(int(part.size) for part in self.parts)

    @functools.cached_property
    def data(self) -> FloatArray:
        """The message's ``data``: the segments concatenated, as float64 (made on first use)."""
        if not self.parts:
            return np.zeros(0)
        return np.concatenate(self.parts, dtype=np.float64)


@dataclass(frozen=True)
class Stamp:
    """A ROS time: whole seconds and nanoseconds."""

    sec: int = 0
    nanosec: int = 0


@dataclass(frozen=True)
class MapMessage:
    """A decoded local or global map message."""

    local_map: LocalMap
    seq: int
    stamp: Stamp
    map_kind: int
    n_submaps: int
    stats: dict[str, float] | None = None
    islands: tuple[int, ...] | None = None
    """Submaps in each island (global maps: the main island first), when the message says."""


@dataclass(frozen=True)
class FeatureMapMessage:
    """A decoded feature-only map message."""

    feature_map: FeatureMap
    seq: int
    stamp: Stamp
    map_kind: int
    n_submaps: int
    stats: dict[str, float] | None = None


@dataclass(frozen=True)
class ChunkMessage:
    """A decoded pose-graph chunk message: the chunk's edges, and the message's seq and stamp.

    Attributes:
        graph: the chunk's edges, named ``"pose-graph chunk <seq>"``.
        seq: sequence number of the chunk.
        stamp: the message's stamp.
    """

    graph: PoseGraph
    seq: int
    stamp: Stamp


_ID_SEGMENTS = frozenset(("header", "var_ids", "islands", "frame_features", "edge_from", "edge_to"))
"""Segments of integers given by the caller (ids, sequence numbers), checked by :func:`_encode`; the
information's indices are below the state's size."""


def _encode(segments: Sequence[tuple[str, npt.ArrayLike]]) -> Encoded:
    """Encode segments as doubles.

    Raises:
        MessageError: an id or header value cannot be carried exactly by a double (|v| >= 2**53).
    """
    arrays = [np.ravel(np.asarray(v, dtype=np.float64) if not isinstance(v, np.ndarray) else v) for _, v in segments]
    for (label, value), array in zip(segments, arrays, strict=True):
        if label in _ID_SEGMENTS and array.size:
            ints = np.asarray(value)
            big = np.abs(ints.astype(np.float64) if ints.dtype.kind == "f" else ints) >= _MAX_EXACT
            if np.any(big):
                raise MessageError(f"segment {label!r}: value {np.ravel(ints)[np.ravel(big)][0]} cannot be carried "
                                   "exactly as a double (|value| >= 2**53)")
    return Encoded(tuple(k for k, _ in segments), tuple(arrays))


def upper_triplets(info: InfoMatrix) -> tuple[npt.NDArray[np.integer[Any]], npt.NDArray[np.integer[Any]], FloatArray]:
    """Return the upper triangle (i <= j) of an information matrix as ``(rows, cols, vals)``.

    The same entries, in the same (row-major) order, as ``scipy.sparse.triu(info, format="coo")``,
    read from the CSR arrays without the full matrix's COO copy: a large map's triangle is made
    in the output thread beside everything the node holds (docs/scale.md, "Peak memory").
    """
    csr = to_csr(info)
    rows = np.repeat(np.arange(csr.shape[0], dtype=csr.indices.dtype), np.diff(csr.indptr))
    upper = csr.indices >= rows
    return rows[upper], csr.indices[upper], csr.data[upper]


def encode_map(
    local_map: LocalMap,
    seq: int,
    stamp: Stamp = Stamp(),
    map_kind: int = MAP_KIND_LOCAL,
    n_submaps: int = 1,
    stats: dict[str, float] | None = None,
    islands: Sequence[int] | None = None,
) -> Encoded:
    """Encode a map into the documented layout (information as upper-triangle triplets)."""
    end = -1 if local_map.end_id is None else local_map.end_id
    header = [FORMAT_VERSION, local_map.dim, map_kind, seq, stamp.sec, stamp.nanosec, local_map.frame_id, end, n_submaps]
    extra_after = [("islands", list(islands))] if islands is not None else []
    return _encode_map_segments(header, local_map.ids, local_map.kinds, local_map.x, local_map.info, stats, (), extra_after)


def encode_feature_map(
    feature_map: FeatureMap,
    seq: int,
    stamp: Stamp = Stamp(),
    map_kind: int = MAP_KIND_GLOBAL,
    n_submaps: int = 1,
    stats: dict[str, float] | None = None,
) -> Encoded:
    """Encode a feature-only map (frame defined by features) into the documented layout."""
    header = [FORMAT_VERSION, feature_map.dim, map_kind, seq, stamp.sec, stamp.nanosec, -1, -1, n_submaps]
    kinds = np.ones(feature_map.ids.size)
    extra = [("frame_features", np.array(feature_map.frame_ids))]
    return _encode_map_segments(header, feature_map.ids, kinds, feature_map.x, feature_map.info, stats, extra)


def _encode_map_segments(
    header: Sequence[int],
    ids: npt.ArrayLike,
    kinds: npt.ArrayLike,
    x: FloatArray,
    info: InfoMatrix,
    stats: dict[str, float] | None,
    extra: Sequence[tuple[str, npt.ArrayLike]] = (),
    extra_after: Sequence[tuple[str, npt.ArrayLike]] = (),
) -> Encoded:
    rows, cols, vals = upper_triplets(info)
    segments: list[tuple[str, npt.ArrayLike]] = [
        ("header", header),
        ("var_ids", ids),
        ("var_kinds", kinds),
        *extra,
        ("state", x),
        ("info_rows", rows),
        ("info_cols", cols),
        ("info_vals", vals),
    ]
    if stats is not None:
        segments.append(("stats", [float(stats.get(k, 0.0)) for k in STATS_FIELDS]))
    segments.extend(extra_after)
    return _encode(segments)


def _segments(
    labels: Sequence[str], sizes: Sequence[int], data: FloatArray, offset: int, required: Sequence[str], what: str
) -> dict[str, FloatArray]:
    """Return each segment of ``data`` by label (views: nothing is allocated from the sizes).

    Checks the layout only; the values' finiteness is :func:`_check_finite`'s, after the
    header and the size limits.
    """
    data = np.asarray(data, dtype=np.float64)
    if offset != 0:
        raise MessageError(f"{what}: layout.data_offset must be 0, got {offset}")
    if len(labels) != len(sizes):
        raise MessageError(f"{what}: {len(labels)} labels for {len(sizes)} sizes")
    declared = [int(s) for s in sizes]
    if any(s < 0 for s in declared):
        raise MessageError(f"{what}: negative segment size in layout {declared}")
    total = sum(declared)
    if total != data.size:
        raise MessageError(f"{what}: layout sizes add up to {total} values but data has {data.size}")
    out: dict[str, FloatArray] = {}
    pos = 0
    for label, size in zip(labels, declared, strict=False):
        if label in out:
            raise MessageError(f"{what}: segment {label!r} appears twice")
        out[label] = data[pos : pos + size]
        pos += size
    missing = [k for k in required if k not in out]
    if missing:
        raise MessageError(f"{what}: missing segment(s) {missing}; labels were {list(labels)}")
    return out


def _check_finite(seg: dict[str, FloatArray], what: str) -> None:
    bad = [k for k, v in seg.items() if not np.isfinite(v).all()]
    if bad:
        raise MessageError(f"{what}: non-finite values in segment(s) {bad}")


def _check_size(quantity: str, value: int, limit_name: str, limits: InputLimits, what: str) -> None:
    fault = size_fault(quantity, value, limit_name, limits)
    if fault is not None:
        raise MessageError(f"{what}: {fault}")


def _check_map_sizes(seg: dict[str, FloatArray], limits: InputLimits, what: str) -> None:
    """Refuse a map message from its declared sizes alone, before any array is built."""
    n = seg["state"].size
    _check_size("state scalars", n, "max_state_scalars", limits, what)
    for name in ("var_ids", "var_kinds", "frame_features"):
        if name in seg:
            _check_size(f"values in segment {name!r}", seg[name].size, "max_state_scalars", limits, what)
    for name in ("info_rows", "info_cols", "info_vals"):
        _check_size(f"information triplets (segment {name!r})", seg[name].size, "max_info_triplets", limits, what)
    rows, cols, vals = (seg[name].size for name in ("info_rows", "info_cols", "info_vals"))
    if not rows == cols == vals:
        raise MessageError(f"{what}: info_rows, info_cols, info_vals sizes differ ({rows}, {cols}, {vals})")
    k = vals
    if k > n * (n + 1) // 2:
        raise MessageError(
            f"{what}: {k} information triplets, more than the {n * (n + 1) // 2} entries of the upper triangle "
            f"of a state of {n} values: some repeat"
        )


def _ints(values: FloatArray, name: str, what: str) -> npt.NDArray[np.int64]:
    if (values != np.round(values)).any() or (np.abs(values) >= _MAX_EXACT).any():
        raise MessageError(f"{what}: segment {name!r} must hold integers")
    return values.astype(np.int64)


_STAMP_SEC_MAX = 2**31 - 1
"""Largest stamp second ``builtin_interfaces/Time.sec`` (int32) holds: the node stamps its outputs with it."""


def _header(seg: dict[str, FloatArray], size: int, what: str) -> npt.NDArray[np.int64]:
    header = seg["header"]
    if header.size < size:
        raise MessageError(f"{what}: header has {header.size} values, format 1 needs {size}")
    _check_finite({"header": header}, what)
    h = _ints(header[:size], "header", what)
    if h[0] != FORMAT_VERSION:
        raise MessageError(f"{what}: unsupported format version {h[0]} (this node reads {FORMAT_VERSION})")
    if h[1] not in (2, 3):
        raise MessageError(f"{what}: dimension must be 2 or 3, got {h[1]}")
    if not 0 <= h[4] <= _STAMP_SEC_MAX or not 0 <= h[5] < 1_000_000_000:
        raise MessageError(f"{what}: invalid stamp {h[4]} s {h[5]} ns (seconds in [0, {_STAMP_SEC_MAX}], "
                           "nanoseconds in [0, 1e9))")
    return h


@dataclass(frozen=True)
class _MapFields:
    dim: int
    map_kind: int
    seq: int
    stamp: Stamp
    frame_pose_id: int
    end_pose_id: int | None
    n_submaps: int
    ids: npt.NDArray[np.int64]
    kinds: npt.NDArray[np.int64]
    state: FloatArray
    info: FloatArray | sp.csr_matrix
    stats: dict[str, float] | None
    segments: dict[str, FloatArray]
    what: str


def symmetric_from_upper(rows: IntArray, cols: IntArray, vals: FloatArray, n: int) -> FloatArray | sp.csr_matrix:
    """Return the symmetric ``(n, n)`` matrix of distinct upper-triangle triplets: dense up to
    :data:`DENSE_MAX` (small systems are solved densely; never above), else CSR."""
    if n <= DENSE_MAX:
        dense = np.zeros((n, n))
        dense[rows, cols] = vals
        dense[cols, rows] = vals
        return dense
    off = rows != cols
    both_rows = np.concatenate([rows, cols[off]])
    both_cols = np.concatenate([cols, rows[off]])
    return sp.csr_matrix((np.concatenate([vals, vals[off]]), (both_rows, both_cols)), shape=(n, n))


def _decode_map_fields(
    labels: Sequence[str], sizes: Sequence[int], data: FloatArray, data_offset: int, limits: InputLimits
) -> _MapFields:
    what = "map message"
    seg = _segments(labels, sizes, data, data_offset, MAP_SEGMENTS, what)
    h = _header(seg, _MAP_HEADER, what)
    dim, map_kind, seq = int(h[1]), int(h[2]), int(h[3])
    if map_kind not in (MAP_KIND_LOCAL, MAP_KIND_GLOBAL):
        raise MessageError(f"{what}: map_kind must be {MAP_KIND_LOCAL} (local) or {MAP_KIND_GLOBAL} (global), got {map_kind}")
    what = f"map message seq {seq}"
    _check_map_sizes(seg, limits, what)
    _check_finite({k: v for k, v in seg.items() if k in _MAP_READ}, what)  # readers ignore other labels
    ids = _ints(seg["var_ids"], "var_ids", what)
    kinds = _ints(seg["var_kinds"], "var_kinds", what)
    if ids.size != kinds.size:
        raise MessageError(f"{what}: {ids.size} var_ids but {kinds.size} var_kinds")
    n = seg["state"].size
    rows = _ints(seg["info_rows"], "info_rows", what)
    cols = _ints(seg["info_cols"], "info_cols", what)
    vals = seg["info_vals"]
    if not rows.size == cols.size == vals.size:
        raise MessageError(f"{what}: info_rows, info_cols, info_vals sizes differ ({rows.size}, {cols.size}, {vals.size})")
    if rows.size and (rows.min() < 0 or cols.min() < 0 or rows.max() >= n or cols.max() >= n):
        raise MessageError(f"{what}: information index out of range for a state of {n} values")
    if np.any(rows > cols):
        raise MessageError(f"{what}: information triplets must be in the upper triangle (row <= col)")
    if np.unique(rows * max(n, 1) + cols).size != rows.size:
        raise MessageError(f"{what}: repeated information entry")
    frame_id, end_id, n_submaps = int(h[6]), int(h[7]), int(h[8])
    if frame_id < -1 or end_id < -1 or n_submaps < 0:
        raise MessageError(f"{what}: header frame_pose_id {frame_id}, end_pose_id {end_id}, n_submaps {n_submaps}: "
                           "pose ids are >= 0 (-1: none) and n_submaps >= 0")
    stored = symmetric_from_upper(rows, cols, vals, n)
    return _MapFields(
        dim, map_kind, seq, Stamp(int(h[4]), int(h[5])), frame_id, None if end_id < 0 else end_id, n_submaps,
        ids, kinds, seg["state"].copy(), stored, _stats(seg), seg, what,
    )


def _stats(seg: dict[str, FloatArray]) -> dict[str, float] | None:
    """Return the ``stats`` segment by field (None when absent or of an unknown length)."""
    if "stats" in seg and STATS_FIELDS_V1 <= seg["stats"].size <= len(STATS_FIELDS):
        return {k: float(v) for k, v in zip(STATS_FIELDS, seg["stats"], strict=False)}
    return None


@dataclass(frozen=True)
class MapSummary:
    """What a map message says of itself in its header and ``stats``, without its map."""

    dim: int
    map_kind: int
    seq: int
    stamp: Stamp
    n_submaps: int
    stats: dict[str, float] | None = None


def decode_map_summary(
    labels: Sequence[str], sizes: Sequence[int], data: FloatArray, data_offset: int = 0
) -> MapSummary:
    """Read a map message's header and ``stats`` only: no array is built and the map is not checked.

    For a reader that waits for a given map (``n_submaps``, ``n_joined``...) among many large
    ones and decodes only that one with :func:`decode_map`: a 72 MB message (60,000 scalars,
    3 M stored entries) took 4.1 s to deserialise, decode and check here, its summary 9 ms.

    Raises:
        MessageError: the layout or the header does not follow the contract.
    """
    what = "map message"
    seg = _segments(labels, sizes, data, data_offset, ("header",), what)
    h = _header(seg, _MAP_HEADER, what)
    return MapSummary(int(h[1]), int(h[2]), int(h[3]), Stamp(int(h[4]), int(h[5])), int(h[8]), _stats(seg))


def submap_of(message: MapMessage) -> LocalMap:
    """Return the local map a decoded ``local_map`` message carries, to be joined.

    Raises:
        MessageError: the message is a global map (``map_kind`` 1, the joiner's own output):
            joined as a submap, every measurement in it would count twice.
    """
    if message.map_kind != MAP_KIND_LOCAL:
        raise MessageError(
            f"{message.local_map.name}: map_kind {message.map_kind} is a global map (a joiner's output); "
            f"only local maps (map_kind {MAP_KIND_LOCAL}) are joined"
        )
    return message.local_map


def decode_map(
    labels: Sequence[str], sizes: Sequence[int], data: FloatArray, data_offset: int = 0, limits: InputLimits | None = None
) -> MapMessage:
    """Decode a local or global map message; validate the map.

    Args:
        labels, sizes, data, data_offset: the message's layout and data.
        limits: size and numeric bounds (default limits when None): the sizes are checked
            from the layout before any array is built, the numbers by the map's validation.

    Raises:
        MessageError: the layout does not follow the contract (names the segment), a size is
            above its limit (names the limit and the value), or the message holds a
            feature-only map (decode it with :func:`decode_feature_map`).
        InvalidMapError: the map itself is invalid (names the map and the fault, a numeric
            limit and the value).
    """
    lim = limits_or_default(limits)
    f = _decode_map_fields(labels, sizes, data, data_offset, lim)
    if "frame_features" in f.segments:
        raise MessageError(f"{f.what}: a feature-only map (segment 'frame_features'); decode it with decode_feature_map")
    if f.frame_pose_id < 0:
        raise MessageError(f"{f.what}: frame_pose_id {f.frame_pose_id}: a map in a pose's frame needs a pose id >= 0")
    name = f"{'local' if f.map_kind == MAP_KIND_LOCAL else 'global'} map seq {f.seq}"
    kinds = f.kinds
    if np.any((kinds != 0) & (kinds != 1)):
        bad = kinds[(kinds != 0) & (kinds != 1)][0]
        raise InvalidMapError(f"local map {name!r}: variable kind must be 0 (pose) or 1 (feature), got {bad}")
    local_map = LocalMap.trusted(f.dim, f.frame_pose_id, f.end_pose_id, f.ids, kinds.astype(np.int8), f.state, f.info, name=name)
    local_map.validate(lim)
    islands = tuple(_ints(f.segments["islands"], "islands", f.what).tolist()) if "islands" in f.segments else None
    return MapMessage(local_map, f.seq, f.stamp, f.map_kind, f.n_submaps, f.stats, islands)


def decode_feature_map(
    labels: Sequence[str], sizes: Sequence[int], data: FloatArray, data_offset: int = 0, limits: InputLimits | None = None
) -> FeatureMapMessage:
    """Decode a feature-only map message (with a ``frame_features`` segment); validate the map.

    Args:
        labels, sizes, data, data_offset: the message's layout and data.
        limits: size and numeric bounds (default limits when None), as in :func:`decode_map`;
            the information is checked as a local map's
            (:func:`linear_slam_ros.core.local_map.check_information`), the coordinates
            against ``max_coordinate``.

    Raises:
        MessageError: the layout does not follow the contract (names the segment), or a size
            is above its limit (names the limit and the value).
        InvalidMapError: the map itself is invalid (names the map and the fault).
    """
    lim = limits_or_default(limits)
    f = _decode_map_fields(labels, sizes, data, data_offset, lim)
    if "frame_features" not in f.segments:
        raise MessageError(f"{f.what}: no 'frame_features' segment: not a feature-only map (decode it with decode_map)")
    frame = _ints(f.segments["frame_features"], "frame_features", f.what)
    if f.frame_pose_id != -1 or f.end_pose_id is not None:
        raise MessageError(f"{f.what}: a feature-only map's frame_pose_id and end_pose_id are -1 (its frame is "
                           f"defined by features), got {f.frame_pose_id} and {-1 if f.end_pose_id is None else f.end_pose_id}")
    if np.any(f.kinds != 1):
        raise InvalidMapError(f"feature-only map seq {f.seq}: every variable must be a feature (kind 1)")
    name = f"feature-only map seq {f.seq}"
    fmap = FeatureMap(f.dim, tuple(int(i) for i in frame), f.ids, f.state, f.info, name=name)
    who = f"feature-only map {name!r}"
    i = first_beyond(fmap.x, np.ones(fmap.x.size, dtype=bool), lim.max_coordinate)
    if i is not None:
        fault = beyond_message(f"coordinate at state index {i}", float(fmap.x[i]), "max_coordinate", lim)
        raise InvalidMapError(f"{who}: {fault}")
    check_information(fmap.info, who, lim)
    return FeatureMapMessage(fmap, f.seq, f.stamp, f.map_kind, f.n_submaps, f.stats)


def encode_chunk(graph: PoseGraph, seq: int, stamp: Stamp = Stamp()) -> Encoded:
    """Encode a pose graph's edges as pose-graph chunk ``seq`` in the documented layout.

    Only the edges travel: poses of ``graph.pose_ids`` that no edge names are not carried.
    """
    header = [FORMAT_VERSION, graph.dim, MAP_KIND_POSE_GRAPH, seq, stamp.sec, stamp.nanosec, graph.n_edges]
    return _encode(
        [
            ("header", header),
            ("edge_from", graph.from_ids),
            ("edge_to", graph.to_ids),
            ("measurement", graph.measurements),
            ("information", graph.information),
        ]
    )


def decode_chunk(
    labels: Sequence[str], sizes: Sequence[int], data: FloatArray, data_offset: int = 0, limits: InputLimits | None = None
) -> ChunkMessage:
    """Decode a pose-graph chunk message.

    Args:
        labels, sizes, data, data_offset: the message's layout and data.
        limits: size and numeric bounds (default limits when None): ``max_chunk_edges`` from
            the header, ``max_state_scalars`` for the local map the chunk makes (``p`` per pose
            other than its frame pose) before the graph is built, the numbers by the graph's
            validation.

    Raises:
        MessageError: the layout does not follow the contract, or a size is above its limit
            (names the limit and the value).
        GraphError: the edges are invalid (see :class:`PoseGraph`; the message names
            ``pose-graph chunk <seq>``).
    """
    lim = limits_or_default(limits)
    what = "pose_graph message"
    seg = _segments(labels, sizes, data, data_offset, CHUNK_SEGMENTS, what)
    h = _header(seg, _CHUNK_HEADER, what)
    if h[2] != MAP_KIND_POSE_GRAPH:
        raise MessageError(f"{what}: map_kind must be {MAP_KIND_POSE_GRAPH} for a pose-graph chunk, got {h[2]}")
    dim, seq, k = int(h[1]), int(h[3]), int(h[6])
    what = f"pose_graph message seq {seq}"
    _check_size("edges", k, "max_chunk_edges", lim, what)
    p = pose_size(dim)
    expected = {"edge_from": k, "edge_to": k, "measurement": k * p, "information": k * p * p}
    for name, size in expected.items():
        if seg[name].size != size:
            raise MessageError(f"{what}: segment {name!r} has {seg[name].size} values, {k} edges need {size}")
    _check_finite(seg, what)
    from_ids = _ints(seg["edge_from"], "edge_from", what)
    to_ids = _ints(seg["edge_to"], "edge_to", what)
    n_poses = int(np.union1d(from_ids, to_ids).size)
    state = max(n_poses - 1, 0) * p  # the local map it makes: every pose but its frame pose
    _check_size(f"state scalars (the local map of a chunk over {n_poses} poses)", state, "max_state_scalars", lim, what)
    graph = PoseGraph.from_edges(
        from_ids,
        to_ids,
        seg["measurement"].reshape(k, p).copy(),
        seg["information"].reshape(k, p, p).copy(),
        dim=dim,
        name=f"pose-graph chunk {seq}",
        limits=lim,
    )
    return ChunkMessage(graph, seq, Stamp(int(h[4]), int(h[5])))
