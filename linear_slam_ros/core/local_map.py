"""The local map value: estimate and information of poses and point features in one pose's frame.

A local map (a submap, or the global map being built) holds variables, each a robot pose or a
point feature, stacked into one state vector, with an information matrix over that vector. All
variables are expressed in the frame of one robot pose, ``frame_id``, which is not itself in the
state. Variables are identified by ``(kind, id)``: pose ids are robot pose indices (``>= 0``),
feature ids are the front-end's landmark ids.
"""

from __future__ import annotations

import dataclasses
import functools
import logging
import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt
import scipy.sparse as sp

from linear_slam_ros.core.errors import InvalidMapError, SolverError
from linear_slam_ros.core.geometry import (
    angle_size,
    canonical_angles3,
    pitch_lock_index,
    pitch_lock_message,
    point_size,
    pose_size,
    wrap_angle,
)
from linear_slam_ros.core.limits import (
    DEFINITE_ONLY,
    InputLimits,
    beyond_message,
    condition_fault,
    first_beyond,
    information_diagonal_fault,
    limits_or_default,
)
from linear_slam_ros.core.solvers import symmetric_splu

logger = logging.getLogger(__name__)

POSE: int = 0
"""Kind code of a robot pose variable."""
FEATURE: int = 1
"""Kind code of a point feature variable."""

ID_BOUND: int = 2**53
"""Every variable id ``i`` has ``|i| < ID_BOUND``: the message layouts carry ids as doubles (exact
below 2**53), and the variable key ``2 i + kind`` must fit an int64."""

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]
InfoMatrix = FloatArray | sp.csr_matrix

_DENSE_CHECK_MAX = 3000
"""Information matrices up to this size are checked densely (Cholesky); larger sparse ones by a
sparse LU with a symmetric fill-reducing ordering, never densified."""
_SYMMETRY_RTOL = 1e-9
_CONDITION_HOW = "1-norm estimate"


def var_keys(ids: npt.ArrayLike, kinds: npt.ArrayLike) -> IntArray:
    """Return the integer key ``2 * id + kind`` that identifies each variable uniquely."""
    return np.asarray(ids, dtype=np.int64) * 2 + np.asarray(kinds, dtype=np.int64)


def pose_key(pose_id: int) -> int:
    """Return the variable key of robot pose ``pose_id``."""
    return 2 * int(pose_id) + POSE


def var_sizes(dim: int, kinds: npt.ArrayLike) -> IntArray:
    """Return the number of scalars of each variable (pose 3/6, feature 2/3)."""
    k = np.asarray(kinds)
    return np.where(k == POSE, pose_size(dim), point_size(dim)).astype(np.int64)


def var_offsets(sizes: IntArray) -> IntArray:
    """Return each variable's first state index, given the variables' sizes."""
    offsets = np.zeros(sizes.size, dtype=np.int64)
    np.cumsum(sizes[:-1], out=offsets[1:])
    return offsets


def scalar_indices(offsets: IntArray, sizes: IntArray, var_indices: npt.ArrayLike) -> IntArray:
    """Return the state indices of variables ``var_indices`` given per-variable offsets and sizes."""
    vi = np.asarray(var_indices, dtype=np.int64)
    s = sizes[vi]
    starts = np.repeat(offsets[vi], s)
    within = np.arange(int(s.sum())) - np.repeat(np.cumsum(s) - s, s)
    return starts + within


def angle_mask(dim: int, kinds: npt.ArrayLike) -> npt.NDArray[np.bool_]:
    """Return a boolean mask over the state vector marking the angle scalars of poses."""
    k = np.asarray(kinds)
    sizes = var_sizes(dim, k)
    offsets = var_offsets(sizes)
    mask = np.zeros(int(sizes.sum()), dtype=bool)
    starts = offsets[k == POSE] + dim
    for j in range(angle_size(dim)):
        mask[starts + j] = True
    return mask


def to_dense(matrix: InfoMatrix) -> FloatArray:
    """Return an information matrix as a dense ``ndarray``."""
    return matrix.toarray() if sp.issparse(matrix) else np.asarray(matrix)


def to_csr(matrix: InfoMatrix) -> sp.csr_matrix:
    """Return an information matrix as CSR."""
    return sp.csr_matrix(matrix) if not sp.issparse(matrix) else matrix.tocsr()


def block_diagonal(blocks: Sequence[InfoMatrix], base: InfoMatrix | None = None) -> sp.csr_matrix:
    """Return the block-diagonal CSR matrix of ``base`` (if any) followed by ``blocks``.

    The same matrix as ``scipy.sparse.block_diag([base, *blocks], format="csr")`` (a dense
    block's zeros left out, a sparse block's stored entries kept, indices sorted), from the
    blocks' arrays directly: no sparse object per block, which costs far more than the
    concatenation for the small blocks of local maps.

    Args:
        blocks: square matrices, dense or sparse.
        base: a matrix to extend, dense or sparse (its arrays are copied, not changed).
    """
    starts: list[IntArray] = []  # each block's row starts in the result's data, its last row's end left out
    indices: list[IntArray] = []
    data: list[FloatArray] = []
    n = nnz = 0
    items = ([] if base is None else [base]) + list(blocks)
    i = 0
    while i < len(items):
        block = items[i]
        if sp.issparse(block):
            csr = block.tocsr()
            if not csr.has_canonical_format:
                csr = csr.copy()
                csr.sum_duplicates()
            ptr = np.asarray(csr.indptr, dtype=np.int64)
            starts.append(ptr[:-1] + nnz)
            indices.append(np.asarray(csr.indices, dtype=np.int64) + n)
            data.append(np.asarray(csr.data, dtype=np.float64))
            n += ptr.size - 1
            nnz += int(ptr[-1])
            i += 1
            continue
        # a run of dense blocks (a stream's local maps: thousands of 3x3 to 18x18 blocks) at once, in the same
        # order as block by block: each block's entries row-major (so sorted), its zeros left out, blocks in turn
        j = i + 1
        while j < len(items) and not sp.issparse(items[j]):
            j += 1
        dense = [np.asarray(block, dtype=np.float64) for block in items[i:j]]
        sizes = np.fromiter((block.shape[0] for block in dense), np.int64, count=len(dense))
        flat = np.concatenate([block.ravel() for block in dense])
        squares = sizes * sizes
        block_of = np.repeat(np.arange(sizes.size), squares)
        within = np.arange(flat.size) - (np.cumsum(squares) - squares)[block_of]
        size_of = sizes[block_of]
        first_row = (np.cumsum(sizes) - sizes)[block_of]
        keep = flat != 0
        rows = first_row[keep] + within[keep] // size_of[keep]
        row_counts = np.bincount(rows, minlength=int(sizes.sum()))
        ends = np.cumsum(row_counts)
        starts.append(ends - row_counts + nnz)
        indices.append(first_row[keep] + within[keep] % size_of[keep] + n)
        data.append(flat[keep])
        n += row_counts.size
        nnz += int(ends[-1]) if ends.size else 0
        i = j
    indptr = np.concatenate([*starts, np.array([nnz], dtype=np.int64)])
    all_indices = np.concatenate(indices) if indices else np.zeros(0, dtype=np.int64)
    out = csr_from_arrays(np.concatenate(data) if data else np.zeros(0), all_indices, indptr, n)
    out.has_canonical_format = True
    return out


def csr_from_arrays(data: FloatArray, indices: IntArray, indptr: IntArray, n: int) -> sp.csr_matrix:
    """Return the ``(n, n)`` CSR matrix of these arrays, with 32-bit indices when they fit (as scipy chooses).

    Args:
        data: ``(nnz,)`` values.
        indices: ``(nnz,)`` column of each value (any integer type).
        indptr: ``(n + 1,)`` where each row starts in ``data`` (any integer type).
        n: the matrix's size.
    """
    if max(n, int(indptr[-1])) <= np.iinfo(np.int32).max:
        return sp.csr_matrix((data, indices.astype(np.int32), indptr.astype(np.int32)), shape=(n, n))
    return sp.csr_matrix((data, indices.astype(np.int64), indptr.astype(np.int64)), shape=(n, n))


def seed_key_lookup(value: Any, keys: IntArray, key_set: dict[int, int]) -> None:
    """Store a map's variable keys and key lookup, computed by the caller, in its caches.

    For maps derived from another (a change of frame, a join), whose lookup follows from the
    other's in O(changes) instead of a dictionary built key by key. ``keys`` and ``key_set``
    must equal what :attr:`VariableLayout.keys` and :attr:`VariableLayout.key_set` would compute.
    """
    cache = vars(value)
    cache["keys"] = keys
    cache["key_set"] = key_set


@dataclass(frozen=True, eq=False)
class StateLayout:
    """Where each variable's scalars sit in the state vector: an explicit, shareable cache.

    Maps with the same ``(dim, kinds)`` (a map and the same map moved to another frame, the
    steps of sequential joining) share one layout object, so its index arrays are computed once,
    when first asked for.

    Attributes:
        dim: 2 or 3.
        kinds: ``(m,)`` variable kinds, :data:`POSE` or :data:`FEATURE`.
        known_sizes: ``(m,)`` the variables' sizes when the caller already has them.
        known_offsets: ``(m,)`` their first state indices when the caller already has them.
    """

    dim: int
    kinds: npt.NDArray[np.int8]
    known_sizes: IntArray | None = dataclasses.field(default=None, repr=False)
    known_offsets: IntArray | None = dataclasses.field(default=None, repr=False)

    @functools.cached_property
    def sizes(self) -> IntArray:
        """``(m,)`` number of scalars of each variable."""
        return self.known_sizes if self.known_sizes is not None else var_sizes(self.dim, self.kinds)

    @functools.cached_property
    def offsets(self) -> IntArray:
        """``(m,)`` index of each variable's first scalar in the state."""
        return self.known_offsets if self.known_offsets is not None else var_offsets(self.sizes)

    @functools.cached_property
    def position_index(self) -> IntArray:
        """``(m, d)`` state indices of every variable's position (feature) or translation (pose)."""
        return self.offsets[:, None] + np.arange(self.dim)

    @functools.cached_property
    def angle_index(self) -> IntArray:
        """``(m_poses, a)`` state indices of every pose's angles, in state order."""
        return self.offsets[self.kinds == POSE][:, None] + np.arange(self.dim, self.dim + angle_size(self.dim))

    @functools.cached_property
    def angles(self) -> npt.NDArray[np.bool_]:
        """``(n,)`` mask of the pose-angle scalars of the state."""
        mask = np.zeros(int(self.sizes.sum()), dtype=bool)
        mask[self.angle_index] = True
        return mask


def replaced_fields(value: Any, changes: Mapping[str, object]) -> dict[str, Any]:
    """Return the fields of a dataclass map with ``changes`` applied, for building its copy.

    The ``layout`` field is dropped (to be rebuilt) when ``dim`` or ``kinds`` change, kept otherwise.
    """
    values = {f.name: getattr(value, f.name) for f in dataclasses.fields(value)}
    values.update(changes)
    if "dim" in changes or "kinds" in changes:
        values["layout"] = None
    return values


class VariableLayout:
    """Layout helpers shared by maps: offsets, keys and index lookups of the variables.

    Mixed into frozen dataclasses that define ``dim``, ``frame_id``, ``ids``, ``kinds``, ``x``,
    ``name`` and ``layout`` (the :class:`StateLayout` of ``dim`` and ``kinds``).
    """

    dim: int
    frame_id: int
    ids: IntArray
    kinds: npt.NDArray[np.int8]
    x: FloatArray
    name: str
    layout: StateLayout

    @property
    def sizes(self) -> IntArray:
        """``(m,)`` number of scalars of each variable."""
        return self.layout.sizes

    @property
    def offsets(self) -> IntArray:
        """``(m,)`` index of each variable's first scalar in :attr:`x`."""
        return self.layout.offsets

    @property
    def position_index(self) -> IntArray:
        """``(m, d)`` state indices of every variable's position (feature) or translation (pose)."""
        return self.layout.position_index

    @property
    def angle_index(self) -> IntArray:
        """``(m_poses, a)`` state indices of every pose's angles, in state order."""
        return self.layout.angle_index

    @property
    def angles(self) -> npt.NDArray[np.bool_]:
        """``(n,)`` mask of the pose-angle scalars of :attr:`x`."""
        return self.layout.angles

    @functools.cached_property
    def keys(self) -> IntArray:
        """``(m,)`` variable keys ``2 * id + kind``."""
        return var_keys(self.ids, self.kinds)

    @functools.cached_property
    def key_set(self) -> dict[int, int]:
        """Hash map from variable key to variable index."""
        return {int(k): i for i, k in enumerate(self.keys.tolist())}

    @property
    def n_vars(self) -> int:
        """Number of variables."""
        return int(self.ids.shape[0])

    @property
    def state_dim(self) -> int:
        """Length of the state vector."""
        return int(self.x.shape[0])

    @property
    def pose_ids(self) -> IntArray:
        """Ids of the pose variables, in state order."""
        return self.ids[self.kinds == POSE]

    @property
    def feature_ids(self) -> IntArray:
        """Ids of the feature variables, in state order."""
        return self.ids[self.kinds == FEATURE]

    def index_of(self, key: int) -> int | None:
        """Return the variable index of ``key`` or ``None``."""
        return self.key_set.get(int(key))

    def has_pose(self, pose_id: int) -> bool:
        """Return whether robot pose ``pose_id`` is a variable of this map."""
        return pose_key(pose_id) in self.key_set

    def scalar_slice(self, var_index: int) -> slice:
        """Return the slice of :attr:`x` holding variable ``var_index``."""
        off = int(self.offsets[var_index])
        return slice(off, off + int(self.sizes[var_index]))

    def scalar_index(self, var_indices: npt.ArrayLike | None = None) -> IntArray:
        """Return the state indices of the given variables (all, in order, when ``None``)."""
        if var_indices is None:
            return np.arange(self.state_dim, dtype=np.int64)
        return scalar_indices(self.offsets, self.sizes, var_indices)

    def pitch_lock_fault(self) -> str | None:
        """Return why the first 3D pose at the Euler angles' singularity (pitch +-90 deg in this map's
        frame) cannot be joined, or None (:func:`pitch_lock_fault`)."""
        if self.dim != 3:
            return None
        return pitch_lock_fault(self.name, self.frame_id, self.x, self.angle_index, self.pose_ids)

    def pose(self, pose_id: int) -> FloatArray:
        """Return a copy of pose ``pose_id`` (``(3,)`` or ``(6,)``); the frame pose is the origin."""
        if pose_id == self.frame_id:
            return np.zeros(pose_size(self.dim))
        idx = self.index_of(pose_key(pose_id))
        if idx is None:
            raise KeyError(f"pose {pose_id} is not in map {self.name!r}")
        return self.x[self.scalar_slice(idx)].copy()


@dataclass(frozen=True, eq=False)
class LocalMap(VariableLayout):
    """Estimate and information of a set of poses and features, in the frame of one pose.

    Constructing a ``LocalMap`` validates it; :meth:`trusted` skips validation for results the
    core computed itself.

    Attributes:
        dim: 2 or 3.
        frame_id: id of the robot pose whose frame the variables are expressed in; not a variable.
        end_id: id of the newest robot pose of the map (a pose variable, or the frame pose itself
            for a map held in its robocentric end-pose frame); ``None`` when not known.
        ids: ``(m,)`` variable ids.
        kinds: ``(m,)`` variable kinds, :data:`POSE` or :data:`FEATURE`.
        x: ``(n,)`` state vector: each pose ``x y phi`` (2D) or ``x y z alpha beta gamma`` (3D),
            each feature ``x y [z]``, in metres and radians, in the frame of ``frame_id``.
        info: ``(n, n)`` symmetric positive-definite information matrix, dense or CSR.
        name: label used in error messages (e.g. ``"localmap_12"``).
        layout: the state layout of ``dim`` and ``kinds`` (built when not given; pass one to
            share it with a map of the same kinds).
    """

    dim: int
    frame_id: int
    end_id: int | None
    ids: IntArray
    kinds: npt.NDArray[np.int8]
    x: FloatArray
    info: InfoMatrix
    name: str = "map"
    layout: StateLayout = dataclasses.field(default=None, repr=False)  # type: ignore[assignment]

    def __post_init__(self) -> None:
        object.__setattr__(self, "ids", np.ascontiguousarray(self.ids, dtype=np.int64))
        object.__setattr__(self, "kinds", np.ascontiguousarray(self.kinds, dtype=np.int8))
        object.__setattr__(self, "x", np.ascontiguousarray(self.x, dtype=np.float64))
        object.__setattr__(self, "layout", StateLayout(self.dim, self.kinds))
        self.validate()
        if self.dim == 3:
            self._canonical_orientations()

    def _canonical_orientations(self) -> None:
        """Give every 3D pose its canonical Euler triple (:func:`~linear_slam_ros.core.geometry.canonical_angles3`),
        its information's ``beta`` row and column negated (exact: the change is affine); the caller's arrays
        are not changed. On construction: a map's triples reach every join and the refinement canonical."""
        index = self.angle_index
        angles, flip = canonical_angles3(self.x[index])
        if not flip.any():
            return
        x = self.x.copy()
        x[index[flip]] = angles[flip]
        sign = np.ones(x.size)
        sign[index[flip, 1]] = -1.0
        info: InfoMatrix
        if sp.issparse(self.info):
            csr = sp.csr_matrix(self.info, copy=True)
            rows = np.repeat(np.arange(x.size), np.diff(csr.indptr))
            csr.data = csr.data * sign[rows] * sign[csr.indices]
            info = csr
        else:
            info = np.asarray(self.info, dtype=np.float64) * sign[:, None] * sign[None, :]
        object.__setattr__(self, "x", x)
        object.__setattr__(self, "info", info)
        logger.debug("%s: %d pose(s) given by the other Euler triple of their rotation, made canonical",
                     self.name, int(flip.sum()))

    def __reduce__(self) -> tuple[Callable[..., LocalMap], tuple[object, ...]]:
        """Pickle the fields only (another process: the refiner's): the layout and the cached lookups are
        rebuilt when first asked for there, at half the cost of pickling them with the map."""
        return _trusted_map, (self.dim, self.frame_id, self.end_id, self.ids, self.kinds, self.x, self.info, self.name)

    @classmethod
    def trusted(
        cls,
        dim: int,
        frame_id: int,
        end_id: int | None,
        ids: IntArray,
        kinds: npt.NDArray[np.int8],
        x: FloatArray,
        info: InfoMatrix,
        name: str = "map",
        layout: StateLayout | None = None,
    ) -> LocalMap:
        """Build a map without validation (for values computed by the core itself).

        ``layout`` is shared when given (it must be that of ``dim`` and ``kinds``).
        """
        obj = object.__new__(cls)
        for field, value in (
            ("dim", dim),
            ("frame_id", int(frame_id)),
            ("end_id", None if end_id is None else int(end_id)),
            ("ids", ids),
            ("kinds", kinds),
            ("x", x),
            ("info", info),
            ("name", name),
            ("layout", layout if layout is not None else StateLayout(dim, kinds)),
        ):
            object.__setattr__(obj, field, value)
        return obj

    def replace(self, **changes: object) -> LocalMap:
        """Return a copy with some fields changed, without re-validating (the layout is shared
        unless ``dim`` or ``kinds`` change)."""
        return LocalMap.trusted(**replaced_fields(self, changes))

    def restricted(self, var_indices: npt.ArrayLike, info: InfoMatrix) -> LocalMap:
        """Return the map of the variables ``var_indices`` (estimate unchanged) with information ``info``.

        Its end pose stays when it is among them (or is the frame pose); else it has none.
        ``info`` (of their scalars, in order) is the caller's: cut out, or marginalised.
        """
        keep = np.asarray(var_indices, dtype=np.int64)
        ids, kinds = self.ids[keep], self.kinds[keep]
        end_id = self.end_id
        if end_id is not None and end_id != self.frame_id and not np.any((ids == end_id) & (kinds == POSE)):
            end_id = None
        return LocalMap.trusted(self.dim, self.frame_id, end_id, ids, kinds, self.x[self.scalar_index(keep)], info, self.name)

    # ------------------------------------------------------------------ validation

    def validate(self, limits: InputLimits | None = None) -> None:
        """Check every invariant; raise :class:`InvalidMapError` naming the map and the fault.

        Besides the structure (ids, kinds, shapes, finiteness, a symmetric positive-definite
        information), the numbers must be joinable in double precision (``limits``, default
        :data:`linear_slam_ros.core.limits.DEFAULT_LIMITS`): pose angles within ``max_angle``,
        coordinates within ``max_coordinate``, and the information as in
        :func:`check_information`. Construction validates with the default limits; the message
        decoders validate again with theirs.
        """
        who = f"local map {self.name!r}"
        if self.dim not in (2, 3):
            raise InvalidMapError(f"{who}: dimension must be 2 or 3, got {self.dim!r}")
        if self.ids.ndim != 1 or self.kinds.shape != self.ids.shape:
            raise InvalidMapError(
                f"{who}: ids and kinds must be 1-D of equal length, got {self.ids.shape} and {self.kinds.shape}"
            )
        bad_kind = ~np.isin(self.kinds, (POSE, FEATURE))
        if bad_kind.any():
            raise InvalidMapError(f"{who}: variable kind must be 0 (pose) or 1 (feature), got {self.kinds[bad_kind][0]}")
        neg = (self.ids < 0) & (self.kinds == POSE)
        if neg.any():
            raise InvalidMapError(f"{who}: pose ids must be >= 0, got {self.ids[neg][0]}")
        huge = (self.ids >= ID_BOUND) | (self.ids <= -ID_BOUND)
        if huge.any() or not -ID_BOUND < self.frame_id < ID_BOUND:
            bad = self.ids[huge][0] if huge.any() else self.frame_id
            raise InvalidMapError(f"{who}: id {bad} is out of range (|id| < 2**53)")
        keys = self.keys
        if len(np.unique(keys)) != len(keys):
            uniq, counts = np.unique(keys, return_counts=True)
            dup = int(uniq[counts > 1][0])
            raise InvalidMapError(f"{who}: duplicate variable {_describe_key(dup)}")
        if pose_key(self.frame_id) in self.key_set:
            raise InvalidMapError(f"{who}: frame pose {self.frame_id} is also a variable of the map")
        if self.end_id is not None and self.end_id != self.frame_id and pose_key(self.end_id) not in self.key_set:
            raise InvalidMapError(f"{who}: end pose {self.end_id} is neither the frame pose nor a pose of the map")
        n = int(self.sizes.sum())
        if self.x.shape != (n,):
            raise InvalidMapError(f"{who}: state has shape {self.x.shape}, the variables need ({n},)")
        if self.info.shape != (n, n):
            raise InvalidMapError(f"{who}: information matrix has shape {self.info.shape}, expected ({n}, {n})")
        values = self.info.data if sp.issparse(self.info) else np.asarray(self.info)
        if not np.all(np.isfinite(values)):
            raise InvalidMapError(f"{who}: information matrix has non-finite entries")
        self.check_numbers(limits)

    def check_numbers(self, limits: InputLimits | None = None, blocks: FloatArray | None = None) -> None:
        """Check the part of :meth:`validate` that is about numbers, for a map whose structure is right.

        The estimate must be finite with pose angles within ``max_angle`` and coordinates within
        ``max_coordinate``, 3D poses off the Euler angles' singularity (pitch not within about 1e-6 rad
        of +-pi/2: :data:`~linear_slam_ros.core.geometry.PITCH_LOCK_COS`), and the information must
        pass :func:`check_information` (with ``blocks``, the ``(m, p, p)`` diagonal blocks of a
        block-diagonal information already known symmetric and positive definite:
        :func:`check_block_diagonal_information`, from the blocks alone).

        Raises:
            InvalidMapError: the first fault, naming the map and the state entry.
        """
        who = f"local map {self.name!r}"
        if not np.all(np.isfinite(self.x)):
            bad = int(np.flatnonzero(~np.isfinite(self.x))[0])
            raise InvalidMapError(f"{who}: state entry {bad} is not finite ({self.x[bad]})")
        lim = limits_or_default(limits)
        angles = self.angles
        for mask, what, limit_name in ((angles, "angle", "max_angle"), (~angles, "coordinate", "max_coordinate")):
            i = first_beyond(self.x, mask, float(getattr(lim, limit_name)))
            if i is not None:
                where = f"{what} at state index {i} ({self._describe_index(i)})"
                raise InvalidMapError(f"{who}: {beyond_message(where, float(self.x[i]), limit_name, lim)}")
        fault = self.pitch_lock_fault()
        if fault is not None:
            raise InvalidMapError(f"local {fault}")
        if blocks is None:
            condition = check_information(self.info, who, lim, self._describe_index)
        else:
            condition = check_block_diagonal_information(blocks, who, lim, self._describe_index)
        self.__dict__["condition_estimate"] = condition  # the cached property, known now at no cost

    @functools.cached_property
    def condition_estimate(self) -> float:
        """The information's condition number, as :func:`check_information` estimates it (1-norm), kept
        from validation (computed when first asked for a map made without it).

        Raises:
            InvalidMapError: the information is not positive definite.
        """
        return check_information(self.info, f"local map {self.name!r}", DEFINITE_ONLY)

    def _describe_index(self, i: int) -> str:
        var = int(np.searchsorted(self.offsets, i, side="right")) - 1
        return _describe_key(int(self.keys[var]))

    def info_dense(self) -> FloatArray:
        """Return the information matrix as a dense array."""
        return to_dense(self.info)

    def info_nnz(self) -> int:
        """Return the number of stored non-zeros of the information matrix (dense: exact count)."""
        if sp.issparse(self.info):
            return int(self.info.count_nonzero())
        return int(np.count_nonzero(self.info))

    @property
    def nbytes(self) -> int:
        """Bytes of the map's arrays: estimate, ids, kinds and information (dense, or CSR's three arrays)."""
        info = self.info
        info_bytes = info.nbytes if isinstance(info, np.ndarray) else info.data.nbytes + info.indices.nbytes + info.indptr.nbytes
        return int(self.x.nbytes + self.ids.nbytes + self.kinds.nbytes + info_bytes)


def _trusted_map(
    dim: int, frame_id: int, end_id: int | None, ids: IntArray, kinds: npt.NDArray[np.int8], x: FloatArray,
    info: InfoMatrix, name: str,
) -> LocalMap:
    """Unpickle a :class:`LocalMap` (:meth:`LocalMap.__reduce__`): it was valid when pickled."""
    return LocalMap.trusted(dim, frame_id, end_id, ids, kinds, x, info, name)


def pitch_lock_fault(name: str, frame_id: int, x: FloatArray, angle_index: IntArray, pose_ids: IntArray) -> str | None:
    """Return why the first 3D pose at the Euler angles' singularity cannot be joined, or None.

    Args:
        name: the map's name; ``frame_id``: the pose whose frame ``x`` is in.
        x: the state vector; ``angle_index``: ``(m_poses, 3)`` state indices of each pose's
            ``(alpha, beta, gamma)``; ``pose_ids``: ``(m_poses,)`` the poses' ids, in that order.

    A pose is at the singularity when ``|cos beta|`` is below
    :data:`~linear_slam_ros.core.geometry.PITCH_LOCK_COS` (pitch within about 1e-6 rad of +-pi/2).
    """
    i = pitch_lock_index(x[angle_index])
    if i is None:
        return None
    beta = int(angle_index[i, 1])
    what = f"pose {int(pose_ids[i])} (state index {beta}) in the frame of pose {frame_id}"
    return f"map {name!r}: {pitch_lock_message(what, abs(math.cos(x[beta])))}"


def _describe_key(key: int) -> str:
    kind = "pose" if key % 2 == POSE else "feature"
    return f"{kind} {key // 2}"


def check_information(
    info: InfoMatrix, who: str, limits: InputLimits | None = None, describe: Callable[[int], str] | None = None
) -> float:
    """Check that an information matrix is symmetric, positive definite and joinable.

    Joinable (``limits``, default :data:`linear_slam_ros.core.limits.DEFAULT_LIMITS`): every
    diagonal entry within ``[min_information, max_information]`` and the condition number,
    estimated in the 1-norm from the factor that proves positive definiteness (LAPACK ``pocon``
    on a dense Cholesky factor; Hager's estimator on a sparse LU factor), at most
    ``max_condition``. Sparse matrices above ``_DENSE_CHECK_MAX`` scalars are never densified.

    Args:
        info: ``(n, n)`` the matrix, dense or sparse.
        who: the prefix of every error (``"local map 'name'"``).
        limits: the bounds (default limits when None).
        describe: what state index ``i`` belongs to (``"pose 3"``), for the messages.

    Returns:
        The condition number estimate (1 for an empty matrix).

    Raises:
        InvalidMapError: the first property that fails, prefixed by ``who``.
    """
    import scipy.linalg  # on first use: the refiner's process never validates a map (0.1 s of its start-up)
    import scipy.linalg.lapack
    import scipy.sparse.linalg as spla

    lim = limits_or_default(limits)
    n = info.shape[0]
    if n == 0:
        return 1.0
    if sp.issparse(info):
        asym = abs(info - info.T)
        scale = abs(info).max()
        asym_max = asym.max() if asym.nnz else 0.0
        diagonal = np.asarray(info.diagonal(), dtype=np.float64)
    else:
        a = np.asarray(info)
        scale = np.abs(a).max()
        asym_max = np.abs(a - a.T).max()
        diagonal = np.diag(a)
    if asym_max > _SYMMETRY_RTOL * max(scale, 1e-300):
        raise InvalidMapError(f"{who}: information matrix is not symmetric (max |I - I^T| = {asym_max:.3g})")
    if np.any(diagonal <= 0):
        raise InvalidMapError(f"{who}: information matrix is not positive definite")
    fault = information_diagonal_fault(diagonal, lim, describe)
    if fault is not None:
        raise InvalidMapError(f"{who}: {fault}")
    if not sp.issparse(info) or n <= _DENSE_CHECK_MAX:
        dense = to_dense(info)
        try:
            factor = scipy.linalg.cholesky(dense, lower=True, check_finite=False)
        except np.linalg.LinAlgError:
            raise InvalidMapError(f"{who}: information matrix is not positive definite") from None
        rcond, _ = scipy.linalg.lapack.dpocon(factor, float(np.abs(dense).sum(axis=0).max()), uplo="L")
        condition = 1.0 / rcond if rcond > 0 else np.inf
    else:
        csc = sp.csc_matrix(info)
        try:
            lu = symmetric_splu(csc)
        except SolverError as exc:
            raise InvalidMapError(f"{who}: {exc}") from None
        condition = float(spla.norm(csc, 1)) * _inverse_one_norm(lu.solve, n)
    fault = condition_fault(condition, _CONDITION_HOW, lim)
    if fault is not None:
        raise InvalidMapError(f"{who}: {fault}")
    return float(condition)


def check_block_diagonal_information(
    blocks: FloatArray, who: str, limits: InputLimits | None = None, describe: Callable[[int], str] | None = None
) -> float:
    """:func:`check_information`'s bounds for the block-diagonal matrix of ``blocks``, from the blocks alone.

    For a pose-only map made of independent edges (a star pose-graph chunk), whose blocks are
    already known symmetric and positive definite (:class:`linear_slam_ros.pose_graph.graph.PoseGraph`
    checks each edge's; a sum of such blocks is one): every diagonal entry within
    ``[min_information, max_information]`` and the 1-norm condition number, here exact rather
    than estimated, ``||A||_1 ||A^-1||_1 = max_b ||B_b||_1 max_b ||B_b^-1||_1``. Nothing of
    size ``(m p)²`` is formed.

    Args:
        blocks: ``(m, p, p)`` the diagonal blocks.
        who: the prefix of every error.
        limits: the bounds (default limits when None).
        describe: what state index ``i`` belongs to, for the messages.

    Raises:
        InvalidMapError: a bound fails (or a block is singular after all), prefixed by ``who``.
    """
    lim = limits_or_default(limits)
    m, p = blocks.shape[0], blocks.shape[-1]
    if m == 0:
        return 1.0
    fault = information_diagonal_fault(blocks[:, np.arange(p), np.arange(p)].reshape(-1), lim, describe)
    if fault is not None:
        raise InvalidMapError(f"{who}: {fault}")
    return check_block_diagonal_condition(blocks, who, lim)


def check_block_diagonal_condition(blocks: FloatArray, who: str, limits: InputLimits | None = None) -> float:
    """The condition-number part of :func:`check_block_diagonal_information` alone (blocks
    whose diagonal is known within the bounds): ``max_b ||B_b||_1 max_b ||B_b^-1||_1`` at most
    ``max_condition``; returns it.

    Raises:
        InvalidMapError: the condition number is above the bound, or a block is singular.
    """
    lim = limits_or_default(limits)
    if blocks.shape[0] == 0:
        return 1.0
    try:
        inverses = np.linalg.inv(blocks)
    except np.linalg.LinAlgError:
        raise InvalidMapError(f"{who}: information matrix is singular") from None
    condition = float(np.abs(blocks).sum(axis=1).max() * np.abs(inverses).sum(axis=1).max())
    fault = condition_fault(condition, "1-norm", lim)
    if fault is not None:
        raise InvalidMapError(f"{who}: {fault}")
    return condition


def _inverse_one_norm(solve: Callable[[FloatArray], FloatArray], n: int) -> float:
    """Estimate ``||A^-1||_1`` of a symmetric ``A`` from its solves (Hager 1984, Higham 1988).

    Deterministic (LAPACK's ``lacon`` algorithm, as ``pocon`` uses): at most 5 iterations of
    two solves each, plus one for Higham's alternative estimate; a lower bound, in practice
    within a factor of 3.
    """
    x = np.full(n, 1.0 / n)
    estimate = 0.0
    previous = -1
    for _ in range(5):
        y = solve(x)
        estimate = max(estimate, float(np.abs(y).sum()))
        xi = np.where(y >= 0, 1.0, -1.0)
        z = solve(xi)  # A^-T xi = A^-1 xi: A is symmetric
        j = int(np.argmax(np.abs(z)))
        if j == previous or np.abs(z[j]) <= float(z @ x):
            break
        previous = j
        x = np.zeros(n)
        x[j] = 1.0
    alt = np.where(np.arange(n) % 2 == 0, 1.0, -1.0) * (1.0 + np.arange(n) / max(n - 1, 1))
    estimate = max(estimate, 2.0 * float(np.abs(solve(alt)).sum()) / (3.0 * n))
    return estimate


def default_end_pose(frame_id: int, pose_ids: npt.ArrayLike) -> int | None:
    """Return the end pose of a pose-only map: the frame's successor if held, else the largest id."""
    ids = np.asarray(pose_ids, dtype=np.int64)
    if ids.size == 0:
        return None
    return frame_id + 1 if np.any(ids == frame_id + 1) else int(ids.max())


def fuse_repeated(
    name: str, dim: int, var_ids: npt.NDArray[np.int64], kinds: npt.NDArray[np.int8], values: FloatArray, info: FloatArray
) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.int8], FloatArray, FloatArray]:
    """Fuse repeated variables of one file into one (two edges to the same pose, as in Intel).

    Two observations ``z_1, z_2`` of one variable with joint information ``I`` are the linear
    observation ``A v`` with ``A = [E; E]``; they are replaced by the equivalent single one,
    ``I_f = A^T I A`` and ``z_f = I_f^-1 A^T I z``. The objective changes only by a constant,
    ``(z - A z_f)^T I (z - A z_f)``: zero when the repeats agree, as in the benchmark data; it is
    logged with the warning (χ² and g2o output are over the fused map).
    """
    keys = var_keys(var_ids, kinds)
    uniq, first, inverse = np.unique(keys, return_index=True, return_inverse=True)
    order = np.argsort(first)  # keep first-appearance order
    rank = np.empty_like(order)
    rank[order] = np.arange(order.size)
    target = rank[inverse]  # fused variable index of each raw variable
    sizes = np.where(kinds == POSE, pose_size(dim), dim)
    raw_off = var_offsets(sizes)
    fused_kinds = kinds[first[order]]
    fused_ids = var_ids[first[order]]
    fused_sizes = np.where(fused_kinds == POSE, pose_size(dim), dim)
    fused_off = var_offsets(fused_sizes)
    n_raw, n_f = int(sizes.sum()), int(fused_sizes.sum())
    sel = np.zeros((n_raw, n_f))
    z = values.copy()
    for v in range(var_ids.size):
        for j in range(int(sizes[v])):
            sel[raw_off[v] + j, fused_off[target[v]] + j] = 1.0
        first_v = int(first[inverse[v]])
        if first_v != v and kinds[v] == POSE:
            a = slice(raw_off[v] + dim, raw_off[v] + sizes[v])
            ref = z[raw_off[first_v] + dim : raw_off[first_v] + sizes[v]]
            z[a] = ref + wrap_angle(z[a] - ref)
    info_f = sel.T @ info @ sel
    z_f = np.asarray(np.linalg.solve(info_f, sel.T @ (info @ z)), dtype=np.float64)
    residual = z - sel @ z_f
    dropped = float(residual @ info @ residual)
    logger.warning(
        "%s: fused %d repeated variable(s) into one each; where the repeats disagree the objective drops a constant, "
        "here %.6g (a chi2 over this map is that much below one over the file's measurements)",
        name, var_ids.size - uniq.size, dropped,
    )
    return fused_ids, fused_kinds, z_f, 0.5 * (info_f + info_f.T)


