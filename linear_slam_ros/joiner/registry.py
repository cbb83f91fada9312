"""The registry of joining strategies, keyed by (method, map type).

Adding a strategy: write its module under :mod:`linear_slam_ros.joiner.strategies` (a class
following :class:`~linear_slam_ros.joiner.strategy.JoinStrategy`) and add one line to
:data:`STRATEGIES`. The node, the CLI and the benchmark find it here.
"""

from __future__ import annotations

from typing import Any

from linear_slam_ros.core.errors import ConfigError
from linear_slam_ros.joiner.strategies.divide_conquer import BatchDC, OnlineDC
from linear_slam_ros.joiner.strategies.feature_only import FeatureBatchDC, FeatureOnlineDC, FeatureSequential
from linear_slam_ros.joiner.strategies.sequential import Sequential
from linear_slam_ros.joiner.strategy import JoinMethod, JoinStrategy, MapType

AnyStrategy = JoinStrategy[Any, Any]

STRATEGIES: dict[tuple[JoinMethod, MapType], AnyStrategy] = {
    (JoinMethod.SEQUENTIAL, MapType.AS_IS): Sequential(),
    (JoinMethod.ONLINE_DC, MapType.AS_IS): OnlineDC(),
    (JoinMethod.DC, MapType.AS_IS): BatchDC(),
    (JoinMethod.SEQUENTIAL, MapType.FEATURE_ONLY): FeatureSequential(),
    (JoinMethod.ONLINE_DC, MapType.FEATURE_ONLY): FeatureOnlineDC(),
    (JoinMethod.DC, MapType.FEATURE_ONLY): FeatureBatchDC(),
}


def get_strategy(method: JoinMethod | str, map_type: MapType | str = MapType.AS_IS) -> AnyStrategy:
    """Return the strategy registered for ``(method, map_type)``.

    Raises:
        ConfigError: not a method or map type (the message lists the valid values; a ``ValueError``).
    """
    try:
        return STRATEGIES[(JoinMethod(method), MapType(map_type))]
    except ValueError as exc:
        valid = [m.value for m in JoinMethod] if "JoinMethod" in str(exc) else [t.value for t in MapType]
        raise ConfigError(f"{exc}: valid values are {valid}") from None


def methods(map_type: MapType, online_only: bool) -> tuple[JoinMethod, ...]:
    """Return the methods registered for ``map_type`` (only the online ones when asked), in enum order."""
    return tuple(
        m for m in JoinMethod
        if (m, map_type) in STRATEGIES and (STRATEGIES[(m, map_type)].online or not online_only)
    )
