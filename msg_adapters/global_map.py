"""The node's ``global_map`` message for any map type a joining strategy produces.

:func:`encode_global` dispatches on the map's type: pose maps use the local-map layout, feature-only
maps the feature-only layout (:mod:`msg_adapters.layout`). A new map type registers its encoder
here with ``@encode_global.register``.
"""

from __future__ import annotations

import functools

from linear_slam_ros.core.local_map import LocalMap
from linear_slam_ros.feature_only.maps import FeatureMap
from msg_adapters.layout import MAP_KIND_GLOBAL, Encoded, Stamp, encode_feature_map, encode_map


@functools.singledispatch
def encode_global(joined: object, seq: int, stamp: Stamp, n_submaps: int, stats: dict[str, float]) -> Encoded:
    """Encode a joined map as the ``global_map`` message (``map_kind`` 1).

    Args:
        joined: the map (a type registered below).
        seq: sequence number of the last joined submap.
        stamp: the message stamp.
        n_submaps: submaps joined.
        stats: the ``stats`` segment (:meth:`linear_slam_ros.joiner.joiner.Joiner.stats`).

    Raises:
        TypeError: no encoder is registered for the map's type.
    """
    raise TypeError(f"no global_map encoding for {type(joined).__name__}")


@encode_global.register
def _(joined: LocalMap, seq: int, stamp: Stamp, n_submaps: int, stats: dict[str, float]) -> Encoded:
    return encode_map(joined, seq, stamp, MAP_KIND_GLOBAL, n_submaps, stats)


@encode_global.register
def _(joined: FeatureMap, seq: int, stamp: Stamp, n_submaps: int, stats: dict[str, float]) -> Encoded:
    return encode_feature_map(joined, seq, stamp, MAP_KIND_GLOBAL, n_submaps, stats)
