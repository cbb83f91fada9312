"""The joiner's typed configuration: one frozen value, from ROS parameters or command-line options.

Every field of :class:`JoinerConfig` is a node parameter; its metadata (:class:`ParamSpec`)
gives the description, whether it is read-only, its numeric range or its allowed values. The
node declares its parameters from :func:`parameter_specs` and builds the config with
:meth:`JoinerConfig.from_mapping`, which names the parameter, the value and the allowed values
of anything invalid.
"""

from __future__ import annotations

import dataclasses
import enum
import functools
import os
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from linear_slam_ros.core.errors import ConfigError
from linear_slam_ros.core.limits import LIMIT_NAMES, NODE_LIMITS, InputLimits
from linear_slam_ros.joiner.registry import get_strategy, methods
from linear_slam_ros.joiner.robots import robot_slots
from linear_slam_ros.joiner.strategies.sequential import SEQUENTIAL_MAX_SCALARS
from linear_slam_ros.joiner.strategy import FoldStrategy, JoinMethod, MapType


class OutputFrame(enum.StrEnum):
    """Frame of the published global map."""

    END_POSE = "end_pose"
    """Robocentric: the newest end pose."""
    FIRST_POSE = "first_pose"
    """The frame pose of the first joined submap."""


DEFAULT_BACKGROUND_MERGE_SCALARS = 100
"""Online D&C merges above this many state scalars go to the background (a merge of two maps of
~50 scalars each is dense and takes well under a millisecond)."""


@dataclass(frozen=True)
class ParamSpec:
    """How a config field is exposed as a ROS parameter.

    Attributes:
        description: one line for ``ros2 param describe`` and the README table.
        read_only: fixed at start-up.
        bounds: inclusive numeric range, or ``None``.
        path: a file or folder name: a leading ``~`` is expanded to the user's home (no shell does it for a
            parameter file or ``-p``, and the journal would otherwise land in a folder named ``~``).
    """

    description: str
    read_only: bool = False
    bounds: tuple[float, float] | None = None
    path: bool = False


def _param(
    default: Any, description: str, read_only: bool = False, bounds: tuple[float, float] | None = None, path: bool = False,
) -> Any:
    return dataclasses.field(default=default, metadata={"param": ParamSpec(description, read_only, bounds, path)})


@dataclass(frozen=True)
class JoinerConfig:
    """Everything the joiner is configured with (units in the descriptions)."""

    mode: JoinMethod = _param(
        JoinMethod.ONLINE_DC,
        "joining method: 'online-dc' (online divide and conquer: any stream length, large merges in the "
        "background) or 'sequential' (the paper's exact sequential joining: O(n^2) per submap, for maps up to "
        f"{SEQUENTIAL_MAX_SCALARS} state scalars)", read_only=True,
    )
    map_type: MapType = _param(
        MapType.AS_IS,
        "'as-is' joins the submaps' variables; 'feature-only' marginalises the poses of "
        "pose-feature submaps and joins feature-only maps in feature-defined frames (D-SLAM)", read_only=True,
    )
    output_frame: OutputFrame = _param(
        OutputFrame.END_POSE,
        "frame of the global_map message: 'end_pose' (robocentric, newest end pose) or 'first_pose'",
    )
    background_merge_scalars: int = _param(
        DEFAULT_BACKGROUND_MERGE_SCALARS,
        "online-dc: merges of more state scalars than this run on a background thread, so that no arrival waits "
        "for a large merge; 0 runs every merge on arrival", read_only=True, bounds=(0, 1_000_000_000),
    )
    publish_rate: float = _param(2.0, "maximum rate of the output topics, Hz", bounds=(0.05, 100.0))
    map_frame: str = _param("map", "frame_id of the viewing topics (the first pose's frame)")
    queue_depth: int = _param(
        0, "subscription history depth; 0 keeps all (reliable, no submap dropped)", read_only=True, bounds=(0, 1_000_000),
    )
    reorder_window: int = _param(100, "early submaps held while waiting for a missing sequence number", bounds=(1, 1_000_000))
    reorder_timeout: float = _param(
        5.0,
        "seconds a missing sequence number may hold the stream up (from the first submap waiting behind it) before it is "
        "given up",
        bounds=(0.01, 86_400.0),
    )
    reorder_max_bytes: int = _param(
        256 << 20, "bytes the early submaps waiting in the reorder buffer may hold", bounds=(1 << 20, 1 << 40),
    )
    ellipse_max_state: int = _param(
        1500, "largest global state (scalars) for which feature covariance ellipses are drawn", bounds=(0, 1_000_000),
    )
    timing_file: str = _param(
        "", "CSV written at shutdown with each joined submap's arrival time, join time and pose/global_map freshness "
        "(for benchmarks); empty: none", read_only=True, path=True,
    )
    summary_period: float = _param(5.0, "seconds between info-level summary lines and /diagnostics", bounds=(0.1, 3600.0))
    save_directory: str = _param(
        "saved_map", "folder where ~/save_map writes poses.txt, features.txt, a bag and the exact state (state.npz)", path=True,
    )
    state_dir: str = _param(
        "", "folder of the journal and snapshots that survive a crash (resumed at start-up); empty: no persistence",
        read_only=True, path=True,
    )
    snapshot_period: int = _param(
        1000, "joined submaps between snapshots of the exact state in state_dir", bounds=(1, 1_000_000),
    )
    load_path: str = _param("", "state file (state.npz) that ~/load_map loads", path=True)
    initial_map: str = _param(
        "", "state file loaded at start-up, to continue mapping on it (ignored when state_dir holds a state)",
        read_only=True, path=True,
    )
    gate_probability: float = _param(
        0.0,
        "chi-square gate: probability of the NIS quantile a submap's common variables must pass before joining "
        "(failing variables are split off, counted as 'gated'); 0 turns the gate off", bounds=(0.0, 0.999999999),
    )
    hold_closures: bool = _param(
        False,
        "hold forward loop closures (poses a submap measures ahead of the chain, each with information of its own) "
        "until the chain reaches their pose, then join them: the gate can test them, and the linear map of a pose "
        "graph is better; always on while gate_probability > 0", read_only=True,
    )
    robots: tuple[str, ...] = _param(
        (),
        "robot namespaces: with a list, the node subscribes to <robot>/local_map and <robot>/pose_graph for each, "
        "keeps each robot's sequence numbers and pose ids apart (robot k's pose i is k * 2^32 + i in the map; "
        "feature ids are shared) and publishes <robot>/pose; empty: one robot on local_map and pose_graph",
        read_only=True,
    )
    refine: bool = _param(
        False,
        "run Gauss-Newton on eq. (7) over every joined submap in a background process, warm-started from its previous "
        "solution and the linear map, and publish global_map_refined (map_type as-is only)", read_only=True,
    )
    # Input limits (linear_slam_ros.core.limits.InputLimits, same names): a submap beyond one is rejected.
    max_state_scalars: int = _param(
        NODE_LIMITS.max_state_scalars,
        "largest submap accepted, in state scalars (a pose-graph chunk: of the local map it makes); "
        "checked from the message's sizes before anything is allocated", bounds=(1, 100_000_000),
    )
    max_info_triplets: int = _param(
        NODE_LIMITS.max_info_triplets, "most information triplets (upper-triangle non-zeros) of one local_map message",
        bounds=(1, 1_000_000_000),
    )
    max_chunk_edges: int = _param(NODE_LIMITS.max_chunk_edges, "most edges of one pose_graph chunk", bounds=(1, 100_000_000))
    min_information: float = _param(
        NODE_LIMITS.min_information, "smallest diagonal entry of a submap's or an edge's information (1/m^2, 1/rad^2)",
        bounds=(1e-300, 1.0),
    )
    max_information: float = _param(
        NODE_LIMITS.max_information, "largest diagonal entry of a submap's or an edge's information (1/m^2, 1/rad^2)",
        bounds=(1.0, 1e300),
    )
    max_condition: float = _param(
        NODE_LIMITS.max_condition,
        "largest condition number of a submap's information (1-norm estimate) or an edge's (2-norm)", bounds=(1.0, 1e300),
    )
    max_angle: float = _param(
        NODE_LIMITS.max_angle, "largest |angle| of a pose orientation or measured rotation, rad", bounds=(4.0, 1e9),
    )
    max_coordinate: float = _param(
        NODE_LIMITS.max_coordinate, "largest |coordinate| of a position or measured translation, m (maps are robocentric)",
        bounds=(1.0, 1e15),
    )

    @functools.cached_property
    def limits(self) -> InputLimits:
        """The input limits of the ``max_*``/``min_*`` fields (same names), built once per config."""
        return InputLimits(**{name: getattr(self, name) for name in LIMIT_NAMES})

    @classmethod
    def from_mapping(cls, values: Mapping[str, Any], online: bool = True) -> JoinerConfig:
        """Build a config from ``{name: value}`` (missing names keep their defaults).

        Args:
            values: parameter values (enum fields as their string values).
            online: allow only strategies that join as submaps arrive (the node); the CLI
                passes ``False`` to allow batch ones too.

        Raises:
            ConfigError: an unknown name, a value of the wrong type or outside its range, an
                enum value not allowed, or a (mode, map_type) pair with no strategy; the message
                names the parameter, the value and the allowed values.
        """
        unknown = sorted(set(values) - {f.name for f in dataclasses.fields(cls)})
        if unknown:
            raise ConfigError(f"unknown parameter {unknown[0]!r}")
        kwargs: dict[str, Any] = {}
        for f in dataclasses.fields(cls):
            if f.name in values:
                kwargs[f.name] = _convert(f, values[f.name])
        config = cls(**kwargs)
        robot_slots(config.robots)  # names checked: ROS name tokens, no repeats
        if config.robots and config.refine:
            raise ConfigError(f"parameter refine=True is not available with robots={list(config.robots)} (one robot only)")
        if config.refine and config.map_type is not MapType.AS_IS:
            raise ConfigError(f"parameter refine=True needs map_type='as-is', not {config.map_type.value!r}")
        allowed = methods(config.map_type, online_only=online)
        if config.mode not in allowed:
            raise ConfigError(
                f"parameter mode={config.mode.value!r} is not allowed with map_type={config.map_type.value!r}: "
                f"allowed values are {[m.value for m in allowed]}"
            )
        if not config.map_frame:
            raise ConfigError("parameter map_frame='' is not a frame id")
        check_strategy_can(config.mode, config.map_type, config.gate_probability, config.hold_closures)
        return config


def check_strategy_can(
    mode: JoinMethod | str, map_type: MapType | str, gate_probability: float | None, hold_closures: bool | None
) -> None:
    """Refuse a gate or held closures that the strategy of ``(mode, map_type)`` would silently not apply.

    Raises:
        ConfigError: naming the parameter and the strategy.
    """
    strategy = get_strategy(mode, map_type)
    strategy_type: Any = type(strategy)
    method = f"mode {strategy.method.value!r} with map_type {strategy.map_type.value!r}"
    if gate_probability and strategy_type.marginal is FoldStrategy.marginal:
        raise ConfigError(
            f"parameter gate_probability={gate_probability:g}: {method} cannot gate "
            "(use 'online-dc' or 'sequential' with map_type 'as-is')"
        )
    if hold_closures and strategy_type.holds is FoldStrategy.holds:
        raise ConfigError(
            f"parameter hold_closures=True: {method} cannot hold loop closures (it cannot tell which poses the map "
            "holds: use 'online-dc' or 'sequential' with map_type 'as-is')"
        )


def _convert(f: dataclasses.Field[Any], value: Any) -> Any:
    """Return ``value`` as field ``f``'s type, checked against its range or allowed values."""
    spec: ParamSpec = f.metadata["param"]
    default = f.default
    if isinstance(default, enum.Enum):
        enum_type = type(default)
        try:
            return enum_type(value)
        except ValueError:
            allowed = [e.value for e in enum_type]
            raise ConfigError(f"parameter {f.name}={value!r} is not valid: allowed values are {allowed}") from None
    if isinstance(default, tuple):  # a string array
        if not isinstance(value, list | tuple) or not all(isinstance(v, str) for v in value):
            raise ConfigError(f"parameter {f.name}={value!r} must be a list of strings")
        return tuple(value)
    accepted = (int, float) if isinstance(default, float) else type(default)  # an int is a valid float
    if isinstance(value, bool) != isinstance(default, bool) or not isinstance(value, accepted):
        raise ConfigError(f"parameter {f.name}={value!r} must be of type {type(default).__name__}")
    if isinstance(default, float):
        value = float(value)
    if spec.path:
        value = os.path.expanduser(value)
    if spec.bounds is not None and not spec.bounds[0] <= value <= spec.bounds[1]:
        raise ConfigError(f"parameter {f.name}={value!r} is outside its range [{spec.bounds[0]:.12g}, {spec.bounds[1]:.12g}]")
    return value


@dataclass(frozen=True)
class ParameterDeclaration:
    """A node parameter as the node declares it.

    Attributes:
        name: parameter name.
        default: default value, as a ROS parameter value (enums as strings, string arrays as lists).
        spec: description, read-only flag and range.
        choices: allowed string values of an enum parameter (empty otherwise).
    """

    name: str
    default: bool | int | float | str | list[str]
    spec: ParamSpec
    choices: tuple[str, ...] = ()


def parameter_declarations() -> tuple[ParameterDeclaration, ...]:
    """Return the node's parameters, in the order of :class:`JoinerConfig`'s fields."""
    out = []
    for f in dataclasses.fields(JoinerConfig):
        default = f.default
        choices: tuple[str, ...] = ()
        if isinstance(default, enum.Enum):
            choices = tuple(str(e.value) for e in type(default))
            default = default.value
        elif isinstance(default, tuple):  # a string array: a list, as ROS gives it
            default = list(default)
        out.append(ParameterDeclaration(f.name, default, f.metadata["param"], choices))
    return tuple(out)
