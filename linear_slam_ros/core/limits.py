"""Bounds on what a map or pose graph from outside may hold, so that no input can exhaust memory
or poison a joined map with numbers double precision cannot join.

Two kinds of bound, checked in two places:

- **Sizes** (``max_state_scalars``, ``max_info_triplets``, ``max_chunk_edges``): checked by the
  message decoders (``msg_adapters.layout``) from a message's declared segment sizes, before
  any array is built from them.
- **Numbers** (``min_information``, ``max_information``, ``max_condition``, ``max_angle``,
  ``max_coordinate``): checked by the validation of the core values
  (:meth:`linear_slam_ros.core.local_map.LocalMap.validate`, the pose graph's validator), so
  messages, dataset files and g2o files all get them.

Measured on every benchmark dataset of ``shared/datasets`` (README, "Input limits"): local maps
hold at most 75 state scalars and 2,850 information triplets, pose-graph chunks at most 44 edges
(14 per local map), information diagonals lie in [0.58, 1.7e6], local maps' condition numbers
stay below 7e5 and the joined global maps' below 2e11 (1-norm estimates), angles within
[-pi, pi] and coordinates within 260 m. Every default below sits far outside those ranges.
"""

from __future__ import annotations

import dataclasses
import math
import sys
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from linear_slam_ros.core.errors import ConfigError

FloatArray = npt.NDArray[np.float64]


@dataclass(frozen=True)
class InputLimits:
    """Bounds on one input map, pose graph or message.

    The defaults are the decoders' (``msg_adapters``) and the dataset reader's: they admit the
    joined global maps the node publishes (VicPark6898's: 21,292 scalars, 1.2 M triplets; a
    sequential map's information is dense: Intel's 2,826 scalars make 4.0 M triplets). The node
    takes tighter size bounds on the submaps it joins, :data:`NODE_LIMITS`.

    Attributes:
        max_state_scalars: most state scalars of one map (a chunk: of the local map it makes,
            ``p`` per pose other than its frame pose).
        max_info_triplets: most information triplets (upper-triangle non-zeros) of one message.
        max_chunk_edges: most edges of one pose-graph chunk message.
        min_information: smallest allowed diagonal entry of an information matrix, in the map's
            units (1/m², 1/rad²).
        max_information: largest allowed diagonal entry of an information matrix (the
            off-diagonal entries of a positive-definite matrix are bounded by the diagonal).
        max_condition: largest allowed condition number of an information matrix: of each
            edge's ``p x p`` block (2-norm, exact), of a map's whole matrix (1-norm estimate
            from its Cholesky or LU factor, never densifying a large sparse one; exact from the
            blocks for the block-diagonal map of a star pose-graph chunk).
        max_angle: largest allowed ``|angle|`` of a pose orientation (state entries, pose-graph
            measurements), rad. Double spacing at 1e4 rad is 1.8e-12 rad, so sin and cos of
            any allowed angle are exact to 1e-12; 1e4 rad is 1,590 turns of an unwrapped
            heading. At 1e300 the spacing of doubles is far above 2 pi: the angle means nothing.
        max_coordinate: largest allowed ``|coordinate|`` of a position (m), in the frame of a
            robot pose (maps are robocentric, so this bounds a map's extent, not where on Earth
            it is). Larger offsets make the changes of frame and the fusion lose every digit.
    """

    max_state_scalars: int = 100_000
    max_info_triplets: int = 20_000_000
    max_chunk_edges: int = 10_000
    min_information: float = 1e-12
    max_information: float = 1e12
    max_condition: float = 1e14
    max_angle: float = 1e4
    max_coordinate: float = 1e6

    def __post_init__(self) -> None:
        for name in ("max_state_scalars", "max_info_triplets", "max_chunk_edges"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ConfigError(f"input limit {name}={value!r} must be an integer >= 1")
        for name in ("min_information", "max_information", "max_condition", "max_angle", "max_coordinate"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not (math.isfinite(value) and value > 0):
                raise ConfigError(f"input limit {name}={value!r} must be a finite number > 0")
        if self.min_information > self.max_information:
            raise ConfigError(
                f"input limits: min_information={self.min_information:g} is above max_information={self.max_information:g}"
            )
        if self.max_condition < 1:
            raise ConfigError(f"input limit max_condition={self.max_condition:g} must be >= 1")


DEFAULT_LIMITS = InputLimits()
"""The decoders' and the dataset reader's limits (``InputLimits()``)."""

OUTPUT_LIMITS = InputLimits(max_condition=sys.float_info.max)
"""Limits for reading the node's own outputs (``global_map``, ``global_map_refined``): the default
sizes and no condition bound. The change of frame to the newest end pose couples the pose it
replaces with every variable by its lever arm, and a large map's information can exceed the
inputs' bound there although it was solved before that change: sphere2500's online D&C map after
1,432 submaps has condition number 7.6e13 in the 2-norm (2.05e14 estimated in the 1-norm, above
the 1e14 of :data:`DEFAULT_LIMITS`), against 1.8e12 and 4.5e12 one submap before and after. Whoever
joins such a map again raises ``max_condition`` knowingly."""

DEFINITE_ONLY = InputLimits(
    min_information=sys.float_info.min, max_information=sys.float_info.max, max_condition=sys.float_info.max
)
"""Limits that only ask an information matrix to be symmetric and positive definite (no magnitude or
condition bound): for matrices a computation made, such as a map moved to another frame."""

NODE_LIMITS = InputLimits(max_state_scalars=5_000, max_info_triplets=2_000_000)
"""The node's defaults for the submaps it joins (its ``max_*`` parameters): sequential joining
holds a submap's dense covariance (5,000 scalars: 200 MB a copy; two fully overlapping
5,000-scalar submaps peak near 3 GB), and 2 M triplets decode in about 200 MB."""

LIMIT_NAMES: tuple[str, ...] = tuple(f.name for f in dataclasses.fields(InputLimits))
"""The field names, which are also the node's parameter names."""


def limits_or_default(limits: InputLimits | None) -> InputLimits:
    """Return ``limits``, or :data:`DEFAULT_LIMITS` when ``None``."""
    return DEFAULT_LIMITS if limits is None else limits


def size_fault(quantity: str, value: int, limit_name: str, limits: InputLimits) -> str | None:
    """Return why ``value`` (a count of ``quantity``) breaks size limit ``limit_name``, or None:
    ``"<value> <quantity>, above the limit <limit_name> = <limit>"``."""
    limit = getattr(limits, limit_name)
    if value > limit:
        return f"{value} {quantity}, above the limit {limit_name} = {limit}"
    return None


def information_diagonal_fault(
    diagonal: FloatArray, limits: InputLimits, describe: Callable[[int], str] | None = None
) -> str | None:
    """Return why a (positive) information diagonal breaks the magnitude bounds, or None.

    Names the first offending entry (and, with ``describe``, what it belongs to, e.g.
    ``"feature 7"``), its value and the bound.
    """
    d = np.asarray(diagonal, dtype=np.float64)
    low = np.flatnonzero(d < limits.min_information)
    high = np.flatnonzero(d > limits.max_information)
    if not (low.size or high.size):
        return None
    i = int(min(low[0] if low.size else d.size, high[0] if high.size else d.size))
    entry = f"information diagonal entry {i}" + (f" ({describe(i)})" if describe is not None else "")
    if d[i] < limits.min_information:
        return f"{entry} is {d[i]:.3g}, below the limit min_information = {limits.min_information:g}"
    return f"{entry} is {d[i]:.3g}, above the limit max_information = {limits.max_information:g}"


def condition_fault(condition: float, how: str, limits: InputLimits) -> str | None:
    """Return why a condition number (computed ``how``) is above ``max_condition``, or None."""
    if not condition <= limits.max_condition:  # also NaN
        return (
            f"information matrix is too ill-conditioned to join in double precision: condition number "
            f"{condition:.3g} ({how}) is above the limit max_condition = {limits.max_condition:g}"
        )
    return None


def first_beyond(values: FloatArray, mask: npt.NDArray[np.bool_], bound: float) -> int | None:
    """Return the first index where ``mask`` holds and ``|values| > bound``, or None."""
    bad = np.flatnonzero(mask & (np.abs(values) > bound))
    return int(bad[0]) if bad.size else None


def beyond_message(what: str, value: float, limit_name: str, limits: InputLimits) -> str:
    """Return ``"<what> is <value> <unit>, beyond the limit <limit_name> = <bound> <unit>"``.

    ``limit_name`` is ``"max_angle"`` (rad) or ``"max_coordinate"`` (m).
    """
    unit = "rad" if limit_name == "max_angle" else "m"
    return f"{what} is {value:.3g} {unit}, beyond the limit {limit_name} = {getattr(limits, limit_name):g} {unit}"
