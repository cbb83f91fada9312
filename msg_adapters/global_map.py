"""The node's ``global_map`` message for any map type a joining strategy produces.

:func:`encode_global` dispatches on the map's type: pose maps use the local-map layout, feature-only
maps the feature-only layout (:mod:`msg_adapters.layout`). A new map type registers its encoder
here with ``@encode_global.register``.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence

import numpy as np

from linear_slam_ros.core.local_map import LocalMap
from linear_slam_ros.feature_only.maps import FeatureMap
from msg_adapters.layout import MAP_KIND_GLOBAL, Encoded, Stamp, encode_feature_map, encode_map


@functools.singledispatch
def encode_global(
    joined: object, seq: int, stamp: Stamp, n_submaps: int, stats: dict[str, float], islands: Sequence[int] | None = None
) -> Encoded:
    """Encode a joined map as the ``global_map`` message (``map_kind`` 1).

    Args:
        joined: the map (a type registered below).
        seq: sequence number of the last joined submap.
        stamp: the message stamp.
        n_submaps: submaps joined.
        stats: the ``stats`` segment (:meth:`linear_slam_ros.joiner.joiner.Joiner.stats`).
        islands: the ``islands`` segment of pose maps: submaps in each island, the main one first.

    Raises:
        TypeError: no encoder is registered for the map's type.
    """
    raise TypeError(f"no global_map encoding for {type(joined).__name__}")


@encode_global.register
def _(
    joined: LocalMap, seq: int, stamp: Stamp, n_submaps: int, stats: dict[str, float], islands: Sequence[int] | None = None
) -> Encoded:
    return encode_map(joined, seq, stamp, MAP_KIND_GLOBAL, n_submaps, stats, islands)


@encode_global.register
def _(
    joined: FeatureMap, seq: int, stamp: Stamp, n_submaps: int, stats: dict[str, float], islands: Sequence[int] | None = None
) -> Encoded:
    return encode_feature_map(joined, seq, stamp, MAP_KIND_GLOBAL, n_submaps, stats)


def encode_empty_global(result_type: type, seq: int, stamp: Stamp, stats: dict[str, float], dim: int = 2) -> Encoded:
    """Encode the ``global_map`` of a joiner that holds no map (before the first submap, after a reset).

    It has no variable and ``n_submaps`` 0, so a late subscriber of the latched topic sees that
    the map is empty rather than an earlier one; it is in the layout of the joiner's map type
    (``result_type``: ``LocalMap`` or ``FeatureMap``), so the subscriber's decoder reads it.

    Raises:
        TypeError: no empty map is known for ``result_type``.
    """
    empty_of = {
        LocalMap: lambda: LocalMap.trusted(
            dim, 0, None, np.zeros(0, np.int64), np.zeros(0, np.int8), np.zeros(0), np.zeros((0, 0)), "empty global map"
        ),
        FeatureMap: lambda: FeatureMap(dim, (), np.zeros(0, np.int64), np.zeros(0), np.zeros((0, 0)), "empty global map"),
    }
    if result_type not in empty_of:
        raise TypeError(f"no empty global_map for {result_type.__name__}")
    return encode_global(empty_of[result_type](), seq, stamp, 0, stats)
