"""The ``joiner`` ROS 2 node: subscriptions, parameters, publishing; the joining is in the core.

Run with ``ros2 run linear_slam_ros joiner --ros-args --params-file config/joiner.yaml``.
Topics, services and parameters are tabulated in the README.
"""

from __future__ import annotations

import dataclasses
import enum
import gc
import logging
import math
import os
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import rclpy
from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import PoseWithCovarianceStamped
from nav_msgs.msg import Path as PathMsg
from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor, SetParametersResult
from rclpy.clock import Clock, ClockType
from rclpy.duration import Duration
from rclpy.exceptions import InvalidHandle, InvalidParameterTypeException, ParameterException
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.serialization import deserialize_message
from rclpy.subscription import Subscription
from std_msgs.msg import Float64MultiArray
from std_srvs.srv import Trigger
from visualization_msgs.msg import MarkerArray

from linear_slam_ros.core.errors import ConfigError, LinearSlamError, MessageError
from linear_slam_ros.core.limits import InputLimits
from linear_slam_ros.core.local_map import LocalMap
from linear_slam_ros.core.runtime import SHARED_MACHINE_BLAS_THREADS, release_memory, set_blas_threads, tune_allocator
from linear_slam_ros.core.timing import latency, peak_rss_mb
from linear_slam_ros.feature_only.frames import change_feature_frame
from linear_slam_ros.feature_only.maps import FeatureMap
from linear_slam_ros.io.results import write_map, write_tum_stamped
from linear_slam_ros.joiner.config import JoinerConfig, OutputFrame, ParameterDeclaration, parameter_declarations
from linear_slam_ros.joiner.joiner import Joiner, JoinerState, SavedJoiner, current_pose, global_result, robot_poses
from linear_slam_ros.joiner.registry import get_strategy
from linear_slam_ros.joiner.robots import qualify, robot_slots
from linear_slam_ros.joiner.snapshot import SnapshotError, read_snapshot, write_snapshot
from linear_slam_ros.joining.background import MergeWorker
from linear_slam_ros.pose_graph.chunks import chunk_to_local_map
from linear_slam_ros.refinement.online import LinearEstimate, Submission
from linear_slam_ros.refinement.worker import RefineWorker, SinkSpec
from linear_slam_ros.ros.journal import JournalError
from linear_slam_ros.ros.periodic import PeriodicTask, PeriodicThread
from linear_slam_ros.ros.persistence import StateStore
from linear_slam_ros.ros.pose_output import PoseTracker
from linear_slam_ros.ros.process import share_directory
from linear_slam_ros.ros.qos import PROFILE_VARIABLES, inbound_dds_profile, inbound_qos, latched_qos
from linear_slam_ros.ros.raw_publish import publish_serialized
from linear_slam_ros.ros.spin import print_usage_if_asked
from linear_slam_ros.ros.tf_output import TF_PARAMETERS, TfOutput, odom_lookup, tf_sender
from msg_adapters import Encoded, Stamp, decode_chunk, decode_map, submap_of
from msg_adapters.cdr import to_cdr
from msg_adapters.global_map import encode_empty_global, encode_global
from msg_adapters.ros import parts
from msg_adapters.views import MapViews, empty_views, map_views, pose_with_covariance_msg, transform_msg

NODE_NAME = "joiner"
PUBLISH_DUTY = 0.5
"""Largest fraction of wall time spent computing outputs. Their heavy parts (CHOLMOD, sparse
products) leave the interpreter lock to the arrivals, so this bounds the second core's share
taken from the background merges."""
PRUNE_EVERY = 1024
"""Offers between two prunings of the per-sequence-number records (a scan of each: amortised)."""
SNAPSHOT_CHECK_PERIOD = 0.25
"""s between two checks whether a snapshot is due (``snapshot_period`` submaps joined since the last)."""
DRAIN_MAX = 16
"""Messages an inbound subscription's callback takes from its own queue after the one the
executor handed it (:func:`take_queued`): at full speed the executor's own round per message
(wait set, ready scan, a coroutine) took 15% of the arrival thread's time (py-spy). Services
and timers wait at most this many submaps (tens of milliseconds)."""
POSE_COALESCE_S = 0.01
"""s: within one subscription callback's drain (:data:`DRAIN_MAX`), the newest pose waits for the
submaps already queued behind it, at most this long after the oldest one it includes arrived.
A queued submap supersedes the pose before anyone could use it: at full speed, building and
publishing a pose per submap took 10% of the arrival thread (py-spy, city2d-20000)."""
SWITCH_INTERVAL = 0.0005
"""s, the interpreter's thread switch interval: an arrival waits at most this long for the
background merge thread to hand over the interpreter lock (Python's default is 5 ms)."""


class _RosLogHandler(logging.Handler):
    """Forwards the core's log records (``linear_slam_ros.*``) to the node's logger."""

    def __init__(self, node: Node) -> None:
        super().__init__(logging.INFO)
        self._logger = node.get_logger()

    def emit(self, record: logging.LogRecord) -> None:
        message = f"{record.name}: {record.getMessage()}"
        if record.levelno >= logging.ERROR:
            self._logger.error(message)
        elif record.levelno >= logging.WARNING:
            self._logger.warning(message)
        else:
            self._logger.info(message)



def _descriptor(decl: ParameterDeclaration) -> ParameterDescriptor:
    spec = decl.spec
    description = spec.description + (f" (one of {list(decl.choices)})" if decl.choices else "")
    desc = ParameterDescriptor(name=decl.name, description=description, read_only=spec.read_only)
    if spec.bounds is not None and isinstance(decl.default, int) and not isinstance(decl.default, bool):
        desc.integer_range = [IntegerRange(from_value=int(spec.bounds[0]), to_value=int(spec.bounds[1]), step=1)]
    elif spec.bounds is not None:
        low, high = float(spec.bounds[0]), float(spec.bounds[1])
        desc.floating_point_range = [FloatingPointRange(from_value=low, to_value=high, step=0.0)]
    return desc


class JoinerNode(Node):
    """Joins every submap as it arrives and republishes the global map and views."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__(NODE_NAME, **kwargs)
        for decl in (*parameter_declarations(), *TF_PARAMETERS):
            try:
                if isinstance(decl.default, list):
                    self._declare_string_array(decl)
                else:
                    self.declare_parameter(decl.name, decl.default, _descriptor(decl))
            except ParameterException as exc:  # an override of the wrong type or out of range: main() exits with 2
                hint = " (write a floating-point value with a decimal point, e.g. 10.0)" if isinstance(decl.default, float) \
                    and isinstance(exc, InvalidParameterTypeException) else ""
                raise ConfigError(f"parameter {decl.name}: {exc}{hint}") from None
        # Raises ConfigError, naming the parameter, its value and the allowed values: main() exits with 2.
        config = JoinerConfig.from_mapping({
            d.name: self.get_parameter_or(d.name, Parameter(d.name, value=d.default)).value for d in parameter_declarations()
        })
        self.config = config
        # robots: each robot's slot keeps its pose ids apart (README, "Islands and several robots")
        self._slots = robot_slots(config.robots) if config.robots else {"": 0}
        self.add_on_set_parameters_callback(self._on_set_parameters)
        strategy = get_strategy(config.mode, config.map_type)
        tune_allocator(strategy.mmap_threshold)
        set_blas_threads(SHARED_MACHINE_BLAS_THREADS)  # whatever the mode
        self._log_handler = _RosLogHandler(self)
        core_logger = logging.getLogger("linear_slam_ros")
        core_logger.addHandler(self._log_handler)
        core_logger.setLevel(logging.INFO)
        core_logger.propagate = False  # printed once, through ROS

        # Large online-D&C merges run on this thread while arrivals go on (README, "Scale").
        self.worker = MergeWorker() if config.background_merge_scalars > 0 else None
        if self.worker is not None:
            sys.setswitchinterval(SWITCH_INTERVAL)
        self.joiner = Joiner(
            config.mode, config.map_type, reorder_window=config.reorder_window, reorder_timeout=config.reorder_timeout,
            reorder_max_bytes=config.reorder_max_bytes, defer_above=config.background_merge_scalars or None,
            worker=self.worker, gate_probability=config.gate_probability or None,
            hold_closures=config.hold_closures or None,  # False: as the gate (held while it is on)
            robots=config.robots,  # recorded in the state: a restore may not give a robot another's slot
        )
        self.joiner.on_reject = self._on_reject
        self.joiner.on_fused = self._on_fused
        self.n_received = 0
        self.n_offered = 0  # submaps offered to the joiner (decoded), for the records' pruning
        self._version = 0  # bumped on every state change (join, rejection, reset, load); the publisher compares it
        self._published_version = 0  # nothing to publish before the first change
        self._lock = threading.Lock()  # guards (joiner.state, _version) snapshots
        # one snapshot at a time, from taking the state to writing it (the timer's and ~/reset's), so a
        # state taken before a reset can never be written after the reset's snapshot
        self._snapshot_lock = threading.Lock()
        self._next_publish = 0.0
        # Freshness (README, "Scale"): arrival time of each submap, and how long after it the
        # first pose and the first global_map including it were published (s).
        self._arrived: dict[int, float] = {}
        self._fresh_pose: list[float] = []
        self._fresh_map: list[float] = []
        self._pose_seq: dict[str, int] = {}  # each robot's pose last published: submaps joined in its state
        self._data_stamps: dict[int, Stamp] = {}  # message stamps of submaps not joined yet
        self._output_stamp: Stamp | None = None  # the newest joined submap's: the outputs' stamp
        self._poses = PoseTracker()  # the newest pose's exact covariance and the TUM stamps
        self._deferred_pose: tuple[Any, int, int, Time] | None = None  # a global map whose exact covariance is not due yet
        # per robot, the pose a callback's drain holds back (POSE_COALESCE_S): state, submaps it
        # includes, the oldest one's arrival time (s, monotonic)
        self._pending_pose: dict[str, tuple[JoinerState, list[Any], float]] = {}
        self._views_stale = False  # path and features skipped for want of a subscriber (README, "Topics")
        self._view_frame: tuple[int, ...] | None = None  # feature-only: the features whose frame the views keep
        self._pose_cleared = False  # ~/reset: the latched pose still holds the cleared map's (README, "Topics")
        self._tf: TfOutput | None = None  # publish_tf (set below)
        self._views_skipped = 0  # publications that skipped them
        self._summary_counts: tuple[float, ...] | None = None  # what the last summary line said
        self._diag_rejected = 0  # rejections counted at the last /diagnostics
        # per submap with timing_file: [arrival (monotonic s), join ms, pose freshness ms, map freshness ms]
        self._timeline: dict[int, list[float]] | None = {} if config.timing_file else None

        self.store = StateStore(Path(config.state_dir)) if config.state_dir else None
        self._journal_records = 0  # journal records the joiner state includes
        self._snapshot_records = -1  # journal records of the newest snapshot
        self._snapshot_joined = 0  # submaps joined in the newest snapshot
        # a gap given up by the reorder timeout is a decision no journal record holds: snapshot it soon, or a
        # restart would wait for that number again (and join it, late, where this run skipped it)
        self._snapshot_wanted = False
        self._persist_seconds = {"journal": 0.0, "snapshot": 0.0, "restore": 0.0}
        # the same in CPU time of the thread doing it, with the joins' for comparison: wall time around
        # a journal write also counts the wait for the interpreter lock at its system call
        self._cpu_seconds = {"journal": 0.0, "snapshot": 0.0, "join": 0.0}
        # refine: what each submap's join fused goes to the refiner process (README, "Refinement");
        # key -> arrival (monotonic s) until the join (Joiner.on_fused)
        self.refiner: RefineWorker | None = None
        self._refine_waiting: dict[Any, float] = {}
        self._start_state()
        if config.refine:
            self.refiner = RefineWorker(SinkSpec("linear_slam_ros.ros.refine_sink:make_sink", {
                "topic": self.resolve_topic_name("global_map_refined"), "node_name": f"{self.get_name()}_refiner",
                "output_frame": config.output_frame.value,
            }))
            self._refine_prior()

        depth = config.queue_depth
        inbound, latched = inbound_qos(depth), latched_qos()
        for robot in self._slots:  # with robots: each robot's topics in its namespace
            for base in ("local_map", "pose_graph"):
                topic = f"{robot}/{base}" if robot else base
                receive = self._receiver(topic, robot)
                receive.subscription = self.create_subscription(Float64MultiArray, topic, receive, inbound, raw=True)
        self.pub_global = self.create_publisher(Float64MultiArray, "global_map", latched)
        self.pub_path = self.create_publisher(PathMsg, "path", latched)
        self.pub_markers = self.create_publisher(MarkerArray, "features", latched)
        self._pose_pubs = (  # with robots: <robot>/pose each
            {robot: self.create_publisher(PoseWithCovarianceStamped, f"{robot}/pose", latched) for robot in self._slots}
            if config.robots else {"": self.create_publisher(PoseWithCovarianceStamped, "pose", latched)}
        )
        # publish_tf: map_frame -> odom_frame or base_frame at the newest pose (tf2_ros where installed; README, TF)
        self._base_frame = str(self.get_parameter("base_frame").value)
        odom_frame = str(self.get_parameter("odom_frame").value)
        if self.get_parameter("publish_tf").value:
            self._tf = self._tf_output(odom_frame)
        # map -> odom again ahead of the clock between submaps, so map -> base lookups at "now" work (README, TF)
        self._tf_period = float(self.get_parameter("tf_publish_period").value)  # read-only
        self._tf_resender = PeriodicThread(
            [PeriodicTask("tf_resend", lambda: self._tf_period, self._on_tf_timer)], self._on_output_error,
            name="linear_slam_tf",
        ) if self._tf is not None and odom_frame and self._tf_period > 0 else None
        self.pub_diag = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        # The executor (single-threaded: main) takes the arrivals and the services; the outputs, the
        # snapshots and the summary run on their own thread (README, "Scale").
        self.create_service(Trigger, "~/reset", self._on_reset)
        # on the steady clock: reorder_timeout is measured with time.monotonic, and with use_sim_time a ROS-clock
        # timer stops with /clock, so submaps waiting behind a lost number were never joined once a bag ended
        self.expire_timer = self.create_timer(0.25, self._on_expire_timer, clock=Clock(clock_type=ClockType.STEADY_TIME))
        self.create_service(Trigger, "~/save_map", self._on_save_map)
        self.create_service(Trigger, "~/load_map", self._on_load_map)
        # one publication at a time; ~/reset and ~/load_map wait for one under way (it holds the old map)
        self._output_lock = threading.Lock()
        tasks = [PeriodicTask("publish", lambda: 1.0 / self.config.publish_rate, self._on_publish_timer)]
        if self.store is not None:
            tasks.append(PeriodicTask("snapshot", lambda: SNAPSHOT_CHECK_PERIOD, self._on_snapshot_timer))
        first_summary = time.monotonic() + config.summary_period  # an idle start says nothing at once
        tasks.append(PeriodicTask("summary", lambda: self.config.summary_period, self._on_summary_timer, first_summary))
        self._outputs = PeriodicThread(tasks, self._on_output_error, name="linear_slam_outputs")
        # the journal's fsyncs on a thread of their own: behind a publication of seconds (a large map) on the
        # output thread, they came 2-3 s apart, beyond the power-cut bound the README gives
        self._syncer = None if self.store is None else PeriodicThread(
            [PeriodicTask("journal_sync", lambda: SNAPSHOT_CHECK_PERIOD, self._on_sync_timer)], self._on_output_error,
            name="linear_slam_journal_sync",
        )
        self.get_logger().info(
            f"joiner ready: mode={config.mode.value}, map_type={config.map_type.value}, "
            f"output_frame={config.output_frame.value}, map_frame={config.map_frame}, queue_depth={depth or 'keep all'}"
        )

    # ------------------------------------------------------------------ parameters

    def _declare_string_array(self, decl: ParameterDeclaration) -> None:
        """Declare a string-array parameter with its (empty) default as a value.

        Its type cannot be inferred from an empty list (rclpy takes ``[]`` for a byte array), and
        declared by type alone it stays unset when not overridden: ``GetParameters`` (``ros2 param
        get``, ``ros2 param dump``) then answers nothing at all for a request that names it. So it is
        declared writable by type, given its default when unset, then made read-only if it is.
        """
        descriptor = _descriptor(decl)  # rclpy keeps this object: the final one is a copy
        read_only = descriptor.read_only
        descriptor.read_only = False
        self.declare_parameter(decl.name, Parameter.Type.STRING_ARRAY, descriptor)
        declared = self.get_parameter_or(decl.name, None)
        if declared is None or declared.type_ == Parameter.Type.NOT_SET:
            default = decl.default
            assert isinstance(default, list)
            self.set_parameters([Parameter(decl.name, Parameter.Type.STRING_ARRAY, default)])
        if read_only:
            final = _descriptor(decl)
            final.type = Parameter.Type.STRING_ARRAY.value
            self.set_descriptor(decl.name, final)

    def _on_set_parameters(self, params: list[Parameter]) -> SetParametersResult:
        # rclpy's own parameters (use_sim_time, ...) are not the joiner's: rclpy handles them
        fields = {f.name for f in dataclasses.fields(JoinerConfig)}
        mine = {p.name: p.value for p in params if p.name in fields}
        if not mine:
            return SetParametersResult(successful=True)
        try:
            changed = JoinerConfig.from_mapping({**self._config_values(), **mine})
        except ConfigError as exc:
            return SetParametersResult(successful=False, reason=str(exc))
        self.config = changed
        names = set(mine)
        if names & {"output_frame", "map_frame", "ellipse_max_state"}:  # the latched outputs in the new frame now,
            with self._lock:  # not only once another submap arrives (after a bag has ended: never)
                self._version += 1
            if self.refiner is not None and "output_frame" in names:  # global_map_refined follows it
                self.refiner.configure_sink(output_frame=changed.output_frame.value)
        if names & {"output_frame", "map_frame", "ellipse_max_state", "publish_rate", "summary_period"}:
            self._outputs.wake()  # a shorter period applies now, not once the old one has run out
        if names & {"reorder_window", "reorder_timeout", "reorder_max_bytes"}:  # every buffer within them at once
            self._join_and_publish(lambda: self.joiner.set_reorder(
                changed.reorder_window, changed.reorder_timeout, changed.reorder_max_bytes
            ))
        if "gate_probability" in names:  # from the next submap on (closures held from then on too)
            with self._lock:
                self.joiner.set_gate(changed.gate_probability or None)
        return SetParametersResult(successful=True)

    def _config_values(self) -> dict[str, Any]:
        """Return the current configuration as parameter values (enums as strings)."""
        return {
            k: v.value if isinstance(v, enum.Enum) else v for k, v in dataclasses.asdict(self.config).items()
        }

    # ------------------------------------------------------------------ inputs

    def _receiver(self, topic: str, robot: str) -> _Receiver:
        """Return the subscription callback of ``robot``'s ``topic`` (its ``subscription`` is set once created)."""
        return _Receiver(self._receive, self._flush_poses, topic, robot, self.context.ok)

    def _receive(self, topic: str, raw: bytes, robot: str = "") -> None:
        """Decode an inbound message of ``robot``, journal it (with ``state_dir``), then offer it to the joiner."""
        arrived = time.monotonic()
        self.n_received += 1
        try:
            submap, seq, stamp = _decode(topic, raw, self.config.limits)
            submap = qualify(submap, self._slots[robot])
        except LinearSlamError as exc:
            self.joiner.reject("bad_message", f"{topic} rejected: {exc}")
            return
        self._offer(submap, seq, journal=(topic, raw), arrived=arrived, stamp=stamp, robot=robot)

    def _replay(self, topic: str, raw: bytes, index: int) -> None:
        """Offer journal record ``index`` again (recovery): decoded as on arrival, not journaled twice.

        Raises:
            ConfigError: the record no longer decodes (another ``robots`` list, lower input limits):
                skipped, it would be lost for good once the next snapshot counted it.
        """
        robot = topic.rpartition("/")[0]
        try:
            if robot not in self._slots:
                raise MessageError(f"robot {robot!r} is not in robots={list(self.config.robots)}")
            submap, seq, stamp = _decode(topic, raw, self.config.limits)
            submap = qualify(submap, self._slots[robot])
        except LinearSlamError as exc:  # it was decoded when journaled: robots or the limits changed since
            raise ConfigError(
                f"journal record {index} ({topic}) of {self.config.state_dir}/journal no longer decodes: {exc}; start "
                "with the robots and input limits it was journaled with, or with another state_dir (or the record is "
                "damaged: the journal keeps no checksum per record)"
            ) from None
        self._offer(submap, seq, index, stamp=stamp, robot=robot)

    def _offer(
        self, submap: LocalMap, seq: int, record: int | None = None, journal: tuple[str, bytes] | None = None,
        arrived: float | None = None, stamp: Stamp | None = None, robot: str = "",
    ) -> None:
        """Offer a submap of ``robot`` to the joiner; with ``journal``, append its message to the journal first.

        The newest pose is published at once when the submap is joined (``arrived``: its arrival
        time, for the freshness figures). Outputs carry the message ``stamp`` of the newest joined
        submap (the node's clock when that stamp is zero).

        Both happen under the joining lock, so a snapshot always pairs a state with the number of
        journal records it includes. A message the joiner will skip (sequence number already
        handled) is not journaled: replaying it would add nothing. Records per submap are keyed by
        :func:`_key` (the sequence number, with its robot when there are several).
        """
        key = _key(robot, seq)
        with self._lock:
            fresh = not self.joiner.already_handled(seq, robot)  # else the joiner skips it
            if journal is not None and self.store is not None and fresh:
                t0, c0 = time.perf_counter(), time.thread_time()
                record = self.store.journal.append(journal[0], journal[1], time.time_ns())  # receive time, wall clock
                self._persist_seconds["journal"] += time.perf_counter() - t0
                self._cpu_seconds["journal"] += time.thread_time() - c0
            c0 = time.thread_time()
            if self.refiner is not None and fresh:
                self._refine_waiting[key] = arrived if arrived is not None else time.monotonic()
            if stamp is not None and fresh:
                self._data_stamps[key] = stamp
            if arrived is not None and fresh:
                self._arrived[key] = arrived
                if self._timeline is not None:
                    self._timeline[key] = [arrived, np.nan, np.nan, np.nan]
            if fresh:
                self._poses.received(key, submap.end_id)
            joined = [_key(robot, s) for s in self.joiner.offer(submap, seq, robot)]
            self._cpu_seconds["join"] += time.thread_time() - c0
            if record is not None:
                self._journal_records = record + 1
            if joined:
                state = self._record_joined(joined)
            self.n_offered += 1
            if self.n_offered % PRUNE_EVERY == 0:
                self._prune(self._data_stamps, keep_joined=False)
                self._prune(self._arrived, keep_joined=True)  # joined ones wait for their global_map
                self._prune(self._refine_waiting, keep_joined=False)
                waiting = dict.fromkeys(self._poses.pending_seqs)
                self._prune(waiting, keep_joined=False)
                self._poses.forget([s for s in self._poses.pending_seqs if s not in waiting])
        if joined and arrived is not None:  # live arrivals (not the journal's replay at start-up)
            self._coalesce_pose(state, joined, robot, arrived)
        for s in joined:
            self.get_logger().debug(
                f"joined submap seq {s}: {self.joiner.state.n_joined} joined, last join "
                f"{self.joiner.join_seconds[-1] * 1e3:.2f} ms"
            )

    def _record_joined(self, joined: list[Any]) -> JoinerState:
        """Record submaps just joined (keys of :func:`_key`, under the joining lock): their join times, their end
        poses' stamps, the outputs' stamp; return the state that holds them."""
        if self._timeline is not None:
            for s, seconds in zip(joined, self.joiner.join_seconds[-len(joined) :], strict=False):
                if s in self._timeline:
                    self._timeline[s][1] = seconds * 1e3
        self._version += 1
        stamps = [self._data_stamps.pop(s, None) for s in joined]
        self._poses.joined(joined, [self._nanoseconds(s) for s in stamps])
        if stamps[-1] is not None:
            self._output_stamp = stamps[-1]
        return self.joiner.state

    def _on_fused(self, robot: str, seq: int, maps: tuple[LocalMap, ...]) -> None:
        """Send what a join fused to the refiner: exactly the measurements of the joined map (the gate's splits
        and held closures out, released closures in). The joiner calls it under the lock, once per joined submap."""
        arrived = self._refine_waiting.pop(_key(robot, seq), None) if self.refiner is not None else None
        if arrived is None:  # no refiner, or a submap joined before it started (the journal's replay)
            return
        assert self.refiner is not None
        stamp = self._stamp()
        for i, m in enumerate(maps):  # the submap's part, then the held closures released with it
            self.refiner.submit(Submission(seq, m, arrived, (stamp.sec, stamp.nanosec), extra=i > 0))

    def _refine_prior(self) -> None:
        """Give the refiner the current map as its first submap (after a resume or a load): it holds the
        submaps joined before, which the refiner never received."""
        if self.refiner is None:
            return
        with self._lock:
            state = self.joiner.state
        prior = global_result(state, OutputFrame.FIRST_POSE) if state.n_joined else None
        if isinstance(prior, LocalMap):
            stamp = self._stamp()
            self.refiner.submit(Submission(state.last_seq or 0, prior, time.monotonic(), (stamp.sec, stamp.nanosec)))

    def _prune(self, per_seq: dict[int, Any], keep_joined: bool) -> None:
        """Keep a per-sequence-number record bounded against hostile streams (called under the lock).

        Numbers leave the records when their outputs go out; one the reorder buffer dropped (far
        ahead) would stay for ever, and so would a rejected one in ``_data_stamps``. Numbers the
        buffer could never hold are forgotten, and with ``keep_joined`` False those below the next
        expected number too.
        """
        window = self.joiner.reorder_window
        stale = []
        for key in per_seq:
            robot, seq = _robot_seq(key)
            expected = self.joiner.expected_of(robot)
            if seq > expected + 2 * window or (not keep_joined and seq < expected):
                stale.append(key)
        for key in stale:
            del per_seq[key]

    def _on_reject(self, _reason: str, message: str) -> None:
        self.get_logger().warning(message)
        self._version += 1  # the latched statistics count it: republish

    def _on_expire_timer(self) -> None:
        """Give up a missing sequence number that has held the stream up for ``reorder_timeout`` s; the submaps
        that wait behind it are joined then, recorded, and their pose published as on arrival."""
        def expire() -> list[tuple[str, int]]:
            joined = self.joiner.expire()
            if joined and self.store is not None:
                self._snapshot_wanted = True
            return joined

        self._join_and_publish(expire)

    def _join_and_publish(self, join: Callable[[], list[tuple[str, int]]]) -> None:
        """Run ``join`` (a joiner call that joins waiting submaps: ``(robot, seq)`` of each) under the lock;
        record what it joined, and publish each robot's pose, as on arrival."""
        with self._lock:
            joined = join()
            if not joined:
                return
            state = self._record_joined([_key(robot, seq) for robot, seq in joined])
        for robot in dict.fromkeys(robot for robot, _ in joined):
            self._publish_pose(state, [_key(r, seq) for r, seq in joined if r == robot], robot)

    # ------------------------------------------------------------------ services

    def _on_reset(self, _request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        # after a publication under way: it must not bring the cleared map's pose and covariance back
        with self._output_lock:
            try:
                self._reset()
            except OSError as exc:  # start.json not written: nothing was changed
                response.success, response.message = False, f"reset failed, the map is unchanged: {exc}"
                self.get_logger().error(response.message)
                return response
        self._outputs.wake()
        response.success, response.message = True, "global map cleared"
        self.get_logger().info("global map reset")
        return response

    def _reset(self) -> None:
        """Clear the map, the per-submap records and the refiner; snapshot the empty state (under the output lock).

        With ``state_dir``, the journal position of the reset is recorded first (``start.json``): no
        recovery replays the cleared map's records, whatever happens to the next snapshot.

        Raises:
            OSError: ``start.json`` cannot be written (the map is left as it was).
        """
        with self._snapshot_lock, self._lock:  # no snapshot of the old map is written after the mark
            if self.store is not None:
                self.store.mark_start(self._journal_records)
            self.joiner.reset()
            self.n_received = 0
            self._version += 1
            self._forget_submaps()
            self._poses.reset()
            self._pose_cleared = True
        if self.refiner is not None:  # the refiner process ends (tested) and a fresh one starts
            with self._lock:
                self._refine_waiting.clear()
            code = self.refiner.reset()
            self.get_logger().info(f"refiner process restarted (the old one's exit code {code})")
        release_memory()  # the buffers of the cleared map go back to the system
        self._snapshot()  # a resume must not bring the cleared map back
        self._next_publish = 0.0  # late subscribers get the empty map, not the cleared one

    def _forget_submaps(self) -> None:
        """Forget the per-submap records of the map being replaced (reset or load; under the joining lock)."""
        self._arrived.clear()
        self._pose_seq.clear()
        self._view_frame = None  # under the output lock too (reset, load)
        if self._tf is not None:  # the next map's stamps may start earlier
            self._tf.reset()
        self._data_stamps.clear()
        self._output_stamp = None
        self._deferred_pose = None
        self._pending_pose.clear()

    def _on_save_map(self, _request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        with self._lock:
            state = self.joiner.state
            saved = self.joiner.save()
            # seconds + nanoseconds apart: ns * 1e-9 rounds 1700000003.75 to ...03.7500002
            pose_stamps = {pid: ns // 1_000_000_000 + (ns % 1_000_000_000) * 1e-9 for pid, ns in self._poses.pose_stamps.items()}
        folder = Path(self.config.save_directory)
        try:
            joined = global_result(state, OutputFrame.FIRST_POSE)
            if joined is None:
                response.success, response.message = False, "nothing to save: no submap joined yet"
                return response
            write_map(joined, folder, state.first_pose_id)
            if isinstance(joined, LocalMap) and state.first_pose_id is not None:  # poses.tum: the submaps' stamps
                write_tum_stamped(folder / "poses.tum", joined, state.first_pose_id, pose_stamps)  # in the first pose's frame
            from linear_slam_ros.ros.bagio import write_messages

            encoded = self._encode(joined, state, self.joiner.stats())
            write_messages(folder / "global_map_bag", [("global_map", 0, encoded)], latched={"global_map"}, overwrite=True)
            write_snapshot(folder / "state.npz", saved)
        except (LinearSlamError, OSError) as exc:
            response.success, response.message = False, f"save failed: {exc}"
            return response
        response.success, response.message = True, f"saved {state.n_joined} submaps to {folder}"
        return response

    def _on_load_map(self, _request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        path = Path(self.config.load_path)
        if not self.config.load_path:
            response.success, response.message = False, "parameter load_path is empty: set it to a state file (state.npz)"
            return response
        with self._output_lock:  # after a publication of the old map under way, never beside it
            try:
                self._load(path)
            except (LinearSlamError, OSError) as exc:
                response.success, response.message = False, f"load failed: {exc}"
                return response
            self._next_publish = 0.0
            self._publish_due()  # the loaded map, at once
        response.success, response.message = True, f"loaded {self.joiner.state.n_joined} submaps from {path}"
        return response

    # ------------------------------------------------------------------ persistence

    def _start_state(self) -> None:
        """Resume from ``state_dir``, or load ``initial_map``; then open the journal.

        Raises:
            SnapshotError: ``initial_map`` cannot be read (names the file and the problem).
            ConfigError: the saved state was joined with another mode or map type, or robots list
                (:meth:`Joiner.check_restorable`).
        """
        config = self.config
        t0 = time.perf_counter()
        loaded = False
        if self.store is not None and self.store.has_state():
            recovery = self.store.recover(self.joiner, self._replay)
            self._journal_records = recovery.journal_records
            self._snapshot_records, self._snapshot_joined = recovery.snapshot_records, self.joiner.state.n_joined
            self._version += 1  # publish the resumed map at once
            self.get_logger().info(
                f"resumed from {recovery.snapshot or 'an empty map'} and {recovery.replayed} journal record(s) in "
                f"{recovery.seconds:.2f} s: {self.joiner.state.n_joined} submaps joined"
                + (f"; {len(recovery.problems)} problem(s), see the warnings" if recovery.problems else "")
            )
            for line in recovery.problems:
                self.get_logger().warning(line)
            if config.initial_map:
                self.get_logger().warning(f"initial_map {config.initial_map} ignored: state_dir {config.state_dir} holds a state")
        elif config.initial_map:
            self._load(Path(config.initial_map), snapshot=False)
            loaded = True
        self._persist_seconds["restore"] = time.perf_counter() - t0
        if self.store is not None:
            self.store.open_journal(self._journal_records)
            if self._journal_records > max(self._snapshot_records, 0) or loaded:
                self._snapshot()  # so that the next resume need not replay (or lose the loaded map)

    def _load(self, path: Path, snapshot: bool = True) -> None:
        """Replace the joiner state by a saved one (``~/save_map``'s ``state.npz`` or ``--save-state``)."""
        saved = read_snapshot(path)
        if not isinstance(saved, SavedJoiner):
            raise SnapshotError(f"state file {path} holds no joiner state")
        self.joiner.check_restorable(saved)  # ConfigError before anything is recorded: the old map stays
        with self._snapshot_lock, self._lock:  # the new map's start recorded before it replaces the old one
            if self.store is not None:
                self.store.mark_start(self._journal_records, path)
            self.joiner.restore(dataclasses.replace(saved, journal_records=self._journal_records))
            self._forget_submaps()  # the replaced map's: its poses' stamps, its newest pose, its outputs' stamp
            self._poses.reset()  # the loaded map's poses have no stamp (poses.tum leaves them out)
            self._version += 1
        self.get_logger().info(f"loaded {self.joiner.state.n_joined} submaps from {path}")
        if self.refiner is not None:
            self.refiner.reset()
            self._refine_prior()
        if snapshot:
            self._snapshot()

    def _snapshot(self) -> None:
        """Write a snapshot of the current state (with ``state_dir``), outside the joining lock."""
        if self.store is None:
            return
        with self._snapshot_lock:
            with self._lock:
                saved = self.joiner.save(self._journal_records)
                self._snapshot_wanted = False
            t0, c0 = time.perf_counter(), time.thread_time()
            try:
                self.store.journal.sync()  # the snapshot never includes records the disk lacks (appends go on)
                self.store.write_snapshot(saved)
            except LinearSlamError as exc:
                self.get_logger().error(f"snapshot failed (the journal still holds every submap): {exc}")
                return
            self._persist_seconds["snapshot"] += time.perf_counter() - t0
            self._cpu_seconds["snapshot"] += time.thread_time() - c0
            self._snapshot_records = saved.journal_records
            self._snapshot_joined = saved.state.n_joined

    def _on_sync_timer(self) -> None:
        store = self.store
        if store is not None:
            store.journal.maybe_sync()  # off the joining thread; a journal that falls quiet gets synced too

    def _on_snapshot_timer(self) -> None:
        if self.store is None:
            return
        with self._lock:
            due = self._snapshot_wanted or self.joiner.state.n_joined - self._snapshot_joined >= self.config.snapshot_period
        if due:
            self._snapshot()

    def destroy_node(self) -> None:
        """Stop the output thread, snapshot and close the journal (clean shutdown), stop the merge thread, then
        destroy the node."""
        if not self._outputs.stop():
            self.get_logger().warning("the output thread did not stop within 30 s")
        if self._syncer is not None and not self._syncer.stop():
            self.get_logger().warning("the journal's sync thread did not stop within 30 s")
        if self._tf_resender is not None:
            self._tf_resender.stop()
        if self.store is not None:
            self._snapshot()
            self.store.close()
            self.store = None
        if self.worker is not None:
            self.worker.stop()
        if self.refiner is not None:
            code = self.refiner.stop()
            self.get_logger().info(f"refiner process stopped (exit code {code})")
        if self._timeline is not None:
            self._write_timeline(Path(self.config.timing_file))
        logging.getLogger("linear_slam_ros").removeHandler(self._log_handler)
        super().destroy_node()

    # ------------------------------------------------------------------ outputs

    def _stamp(self) -> Stamp:
        """The outputs' stamp: the newest joined submap's message stamp, or the node's clock when it is zero."""
        data = self._output_stamp
        if data is not None and (data.sec, data.nanosec) != (0, 0):
            return data
        now = self.get_clock().now().to_msg()
        return Stamp(int(now.sec), int(now.nanosec))

    def _coalesce_pose(self, state: JoinerState, joined: list[Any], robot: str, arrived: float) -> None:
        """Hold ``robot``'s newest pose back for the submaps queued behind it; publish it once the
        oldest submap it includes arrived :data:`POSE_COALESCE_S` ago (else :meth:`_flush_poses` does,
        when the callback's queue is empty)."""
        pending = self._pending_pose.pop(robot, None)
        if pending is not None:
            joined, arrived = pending[1] + joined, pending[2]
        if time.monotonic() - arrived < POSE_COALESCE_S:
            self._pending_pose[robot] = (state, joined, arrived)
        else:
            self._publish_pose(state, joined, robot)

    def _flush_poses(self) -> None:
        """Publish the poses held back (the callback's queue is empty, or it took :data:`DRAIN_MAX`)."""
        if not self.context.ok():  # shutting down: nothing can be published any more
            self._pending_pose.clear()
            return
        while self._pending_pose:
            robot, (state, joined, _) = self._pending_pose.popitem()
            self._publish_pose(state, joined, robot)

    def _publish_pose(self, state: JoinerState, joined: list[Any], robot: str = "") -> None:
        """Publish ``robot``'s newest pose in a state just joined, if its strategy has it cheaply."""
        current = current_pose(state, robot)  # None while the robot is off the first chain (README, "Islands")
        if current is None:
            return
        end_pose = current[1]
        # the newest exact covariance, of an earlier pose: the exact one follows with the global map (README, pose)
        cov = self._poses.fast_covariance() if not self.config.robots else None
        self._send_pose(end_pose, cov, self._stamp_msg(), robot)
        now = time.monotonic()
        for s in joined:
            t = self._arrived.get(s)
            if t is not None:
                self._fresh_pose.append(now - t)
                if self._timeline is not None and s in self._timeline:
                    self._timeline[s][2] = (now - t) * 1e3
        self._pose_seq[robot] = state.n_joined

    def _send_pose(self, pose: np.ndarray, cov: np.ndarray | None, stamp: Time, robot: str = "") -> None:
        """Publish ``robot``'s newest pose (map frame) with its covariance on ``pose`` and, with ``publish_tf``, on ``/tf``."""
        dim = PoseTracker.pose_dim(pose)
        frame = self.config.map_frame
        self._pose_pubs[robot].publish(pose_with_covariance_msg(dim, pose, cov, frame, stamp))
        if self._tf is not None:
            child = f"{robot}/{self._base_frame}" if robot else self._base_frame
            self._tf.publish(transform_msg(dim, pose, frame, child, stamp))

    def _on_tf_timer(self) -> None:
        """Send the newest ``map -> odom`` again, stamped ``tf_publish_period`` ahead of the node's clock."""
        if self._tf is not None and self.context.ok():
            ahead = Duration(seconds=self._tf_period)
            self._tf.resend((self.get_clock().now() + ahead).to_msg(), self.config.map_frame)

    def _tf_output(self, odom_frame: str) -> TfOutput | None:
        """Return the TF output of ``publish_tf``, or ``None`` (with a warning) when nothing can send it here."""
        send, how = tf_sender(self)
        lookup, how_odom = odom_lookup() if odom_frame and send is not None else (None, "")
        if send is None or (odom_frame and lookup is None):
            self.get_logger().warning(f"publish_tf is set but no TF is published: {how if send is None else how_odom}")
            return None
        base = self._base_frame
        parent = f"{odom_frame} (REP-105, with the odometry's {odom_frame} -> {base})" if odom_frame else base
        self.get_logger().info(f"publish_tf: {self.config.map_frame} -> {parent}, by {how}")

        def warn(message: str) -> None:
            self.get_logger().warning(message, throttle_duration_sec=10.0)

        return TfOutput(send, odom_frame, lookup, warn)

    def _nanoseconds(self, stamp: Stamp | None) -> int:
        """A submap's stamp in ns, the node's clock when it is zero or missing (its end pose's time: ``path``, ``poses.tum``)."""
        if stamp is None or (stamp.sec, stamp.nanosec) == (0, 0):
            return int(self.get_clock().now().nanoseconds)
        return stamp.sec * 1_000_000_000 + stamp.nanosec

    def _stamp_msg(self) -> Any:
        """:meth:`_stamp` as a ``builtin_interfaces/Time``."""
        stamp = self._stamp()
        return Time(sec=stamp.sec, nanosec=stamp.nanosec)

    def _record_map_freshness(self, state: JoinerState) -> None:
        """Count the submaps ``state`` has joined as published in the global map now."""
        now = time.monotonic()
        with self._lock:
            joined = [k for k in self._arrived if _robot_seq(k)[1] <= (state.stream(_robot_seq(k)[0]).last_seq or 0)]
            for s in joined:
                seconds = now - self._arrived.pop(s)
                self._fresh_map.append(seconds)
                if self._timeline is not None and s in self._timeline:
                    self._timeline[s][3] = seconds * 1e3

    def node_stats(self) -> dict[str, float]:
        """Return the node's freshness (ms), background-merge, memory and CPU figures."""
        out: dict[str, float] = {}
        for what, samples in (("pose", self._fresh_pose), ("map", self._fresh_map)):
            lat = latency(samples)
            out[f"freshness_{what}_ms_p50"] = lat.p50_ms
            out[f"freshness_{what}_ms_p99"] = lat.p99_ms
            out[f"freshness_{what}_ms_max"] = lat.max_ms
            out[f"n_fresh_{what}"] = float(len(samples))
        if self.worker is not None:
            out["background_merges"] = float(self.worker.n_done)
            out["background_merge_worker_alive"] = float(self.worker.alive)
            out["background_merge_seconds_total"] = self.worker.seconds
        out["n_views_skipped"] = float(self._views_skipped)
        out["peak_rss_mb"] = peak_rss_mb()
        out["cpu_seconds"] = time.process_time()  # every thread of the process, since it started
        return out

    def _write_timeline(self, path: Path) -> None:
        """Write the per-submap timing CSV (``timing_file``): seq (``robot/seq`` with robots), arrival s (from the
        first), join and freshness ms."""
        rows = sorted(self._timeline.items()) if self._timeline else []
        start = min((r[0] for _, r in rows), default=0.0)
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            with open(path, "w") as fh:
                fh.write("seq,arrival_s,join_ms,pose_freshness_ms,map_freshness_ms\n")
                for key, (arrived, join_ms, pose_ms, map_ms) in rows:
                    robot, seq = _robot_seq(key)
                    label = f"{robot}/{seq}" if robot else str(seq)
                    fh.write(f"{label},{arrived - start:.6f},{join_ms:.4f},{pose_ms:.4f},{map_ms:.4f}\n")
        except OSError as exc:
            self.get_logger().error(f"cannot write timing_file {path}: {exc}")

    def _on_output_error(self, task: str, exc: BaseException) -> None:
        log = self.get_logger().error if self.context.ok() else self.get_logger().debug  # shutting down
        log(f"{task} failed: {type(exc).__name__}: {exc}")

    def _on_publish_timer(self) -> None:
        with self._output_lock:
            self._publish_due()

    def _publish_due(self) -> None:
        """Publish the global map and its views if the state changed and the duty cycle allows."""
        now = time.monotonic()
        if now < self._next_publish:
            return
        with self._lock:
            state, version, stats = self.joiner.state, self._version, self.joiner.stats()
        if version == self._published_version:
            self._publish_deferred_pose()
            self._publish_late_views(state)
            return
        stats.update(self.node_stats())
        try:
            self._publish(state, stats)
        except LinearSlamError as exc:  # outputs of a valid state: the context shut down under it
            log = self.get_logger().error if self.context.ok() else self.get_logger().debug
            log(f"could not publish the global map: {exc}")
        self._published_version = version
        # Outputs of a large map cost CPU the merges need: keep publishing under PUBLISH_DUTY of
        # the time, whatever publish_rate asks for.
        self._next_publish = now + (time.monotonic() - now) / PUBLISH_DUTY

    def _encode(self, joined: Any, state: JoinerState, stats: dict[str, float]) -> Encoded:
        islands = [i.n_submaps for i in state.islands]
        return encode_global(joined, state.last_seq or 0, self._stamp(), state.n_joined, stats, islands)

    def _publish(self, state: JoinerState, stats: dict[str, float]) -> None:
        config = self.config
        stamp = self._stamp_msg()
        newest: tuple[np.ndarray, np.ndarray | None] | None = None
        joined: Any = None
        views: MapViews | None
        self._deferred_pose = None  # the map it holds goes before the new one is made (peak memory); a new one is set below
        if state.n_joined == 0:  # no map (yet, or since a reset): say so, so no earlier map stays latched
            empty = encode_empty_global(state.strategy.result_type, state.last_seq or 0, self._stamp(), stats)
            publish_serialized(self.pub_global, to_cdr(empty))
            views = empty_views(config.map_frame, stamp)
            if self._pose_cleared:  # the latched pose is the cleared map's: now unknown, at the new map's origin
                self._pose_cleared = False
                for publisher in self._pose_pubs.values():
                    publisher.publish(pose_with_covariance_msg(2, np.zeros(3), None, config.map_frame, stamp))
        else:
            joined = global_result(state, config.output_frame)
            if joined is None:  # feature-only: no group defines a feature frame yet
                return
            publish_serialized(self.pub_global, to_cdr(self._encode(joined, state, stats)))
            self._record_map_freshness(state)
            if self.refiner is not None and isinstance(joined, LocalMap):  # the warm start of its new variables
                self.refiner.linear(LinearEstimate.of_map(joined, state.n_joined))
            views = self._map_views(joined, state, stamp) if self._views_wanted() else None
        self._send_views(views)
        # one robot, in the main island: the map's end is where it is (README, "Islands and several robots")
        one_robot_here = not self.config.robots and state.in_main_island()
        if state.n_joined and isinstance(joined, LocalMap) and state.first_pose_id is not None and one_robot_here:
            newest = self._poses.from_map(joined, state.first_pose_id)  # exact covariance when due (README, pose)
            if newest is not None and newest[1] is not None:
                with self._lock:
                    self._poses.set_exact(newest[1], state.n_joined)
            # not due: the exact covariance of this map follows when it is (_publish_deferred_pose)
            deferred = newest is not None and not self._poses.last_exact
            self._deferred_pose = (joined, state.first_pose_id, state.n_joined, stamp) if deferred else None
        else:
            self._deferred_pose = None  # no pose of this map to publish later either
        if self.config.robots and isinstance(joined, LocalMap) and state.first_pose_id is not None:
            self._send_robot_poses(state, joined, stamp)
        if newest is not None and state.n_joined >= self._pose_seq.get("", 0):  # not older than the arrivals' pose
            self._send_pose(newest[0], newest[1], stamp)

    def _views_wanted(self) -> bool:
        """Whether anyone subscribes to ``path`` or ``features`` (building them for 20,000 poses takes 0.35 s of Python)."""
        return self.pub_path.get_subscription_count() > 0 or self.pub_markers.get_subscription_count() > 0

    def _map_views(self, joined: Any, state: JoinerState, stamp: Time) -> MapViews:
        if isinstance(joined, FeatureMap):
            joined = self._in_view_frame(joined)
        with self._lock:
            pose_stamps = dict(self._poses.pose_stamps)
        return map_views(joined, state.first_pose_id, self.config.map_frame, stamp, self.config.ellipse_max_state, pose_stamps)

    def _in_view_frame(self, feature_map: FeatureMap) -> FeatureMap:
        """A feature-only map in the frame of the features that defined the first one viewed (the global map's
        frame features change at merges: drawn in its own frame, the whole map would move at every update)."""
        if self._view_frame is None:
            self._view_frame = feature_map.frame_ids
        try:
            return change_feature_frame(feature_map, self._view_frame)
        except LinearSlamError as exc:
            self.get_logger().warning(
                f"features: cannot keep the frame of features {list(self._view_frame)} ({exc}); "
                f"drawn in the map's frame {list(feature_map.frame_ids)} from now on"
            )
            self._view_frame = feature_map.frame_ids
            return feature_map

    def _send_views(self, views: MapViews | None) -> None:
        """Publish ``path`` (when the map has poses) and ``features``; ``None``: skipped for want of a subscriber."""
        self._views_stale = views is None
        if views is None:
            self._views_skipped += 1
            return
        if views.path is not None:
            self.pub_path.publish(views.path)
        self.pub_markers.publish(views.markers)

    def _publish_late_views(self, state: JoinerState) -> None:
        """Build the views skipped for want of a subscriber once one comes, the map having stopped changing."""
        if not self._views_stale or not self._views_wanted() or state.n_joined == 0:
            return
        try:
            joined = global_result(state, self.config.output_frame)
        except LinearSlamError as exc:  # pragma: no cover - outputs of a valid state
            self._views_stale = False  # said once, not at every tick
            self.get_logger().error(f"could not build the path and features: {exc}")
            return
        self._send_views(self._map_views(joined, state, self._stamp_msg()) if joined is not None else None)

    def _send_robot_poses(self, state: JoinerState, joined: LocalMap, stamp: Time) -> None:
        """Publish each robot's newest pose from the global map (several robots: no covariance, README), unless an
        arrival published a newer one of that robot meanwhile (the map is of an older state)."""
        with self._lock:
            published = dict(self._pose_seq)
        for robot, pose in robot_poses(state, joined).items():
            if state.n_joined >= published.get(robot, 0):
                self._send_pose(pose, None, stamp, robot)

    def _publish_deferred_pose(self) -> None:
        """Publish the exact covariance of the last global map's newest pose once it is due, if it was skipped."""
        if self._deferred_pose is None or not self._poses.exact_due():
            return
        joined, first_pose_id, n_joined, stamp = self._deferred_pose
        self._deferred_pose = None
        newest = self._poses.from_map(joined, first_pose_id)
        if newest is None or newest[1] is None:
            return
        with self._lock:
            self._poses.set_exact(newest[1], n_joined)
        if n_joined >= self._pose_seq.get("", 0):  # no arrival has published a newer pose meanwhile
            self._send_pose(newest[0], newest[1], stamp)

    def _on_summary_timer(self) -> None:
        with self._lock:
            stats, state = self.joiner.stats(), self.joiner.state
            rejected = dict(self.joiner.rejected)
        counts = (stats["n_joined"], stats["n_rejected"], self.joiner.n_skipped, self.n_received)
        if counts != self._summary_counts:  # an idle node says nothing (diagnostics go on)
            self._summary_counts = counts
            self.get_logger().info(
                f"{int(stats['n_joined'])} submaps joined, {int(stats['n_rejected'])} rejected {rejected or ''}, "
                f"last join {stats['last_join_ms']:.2f} ms"
            )
        status = DiagnosticStatus(level=DiagnosticStatus.OK, name=f"{self.get_name()}: joining", hardware_id=self.get_name())
        status.message = "joining" if state.n_joined else "waiting for submaps"
        # the level says how the node is now: WARN while submaps are being rejected, OK again after a quiet
        # period (the totals stay in the values; one lost submap kept it WARN for the process's life)
        recent = int(stats["n_rejected"]) - self._diag_rejected
        self._diag_rejected = int(stats["n_rejected"])
        if recent > 0:
            status.level = DiagnosticStatus.WARN
            period = self.config.summary_period
            status.message = f"{recent} submaps rejected in the last {period:g} s ({self._diag_rejected} in all)"
        stats.update(self.node_stats())
        status.values = [KeyValue(key=k, value=diagnostic_value(v)) for k, v in stats.items()]
        status.values.append(KeyValue(key="n_received", value=str(self.n_received)))
        # by reason (bad_message, invalid_map, late, gap, gated, ...), as the summary line counts them
        status.values.extend(KeyValue(key=f"n_rejected_{reason}", value=str(n)) for reason, n in sorted(rejected.items()))
        status.values.append(KeyValue(key="n_skipped", value=str(self.joiner.n_skipped)))
        status.values.append(KeyValue(key="n_gated", value=str(len(self.joiner.gated))))
        status.values.append(KeyValue(key="n_reinitialised", value=str(len(self.joiner.reinitialised))))
        status.values.append(KeyValue(key="n_held", value=str(len(state.held))))
        if self.joiner.gated:
            last = self.joiner.gated[-1]
            status.values.append(KeyValue(key="last_gated", value=last.describe()))
        for what, seconds in self._persist_seconds.items():
            status.values.append(KeyValue(key=f"{what}_seconds_total", value=diagnostic_value(seconds)))
        for what, seconds in self._cpu_seconds.items():
            status.values.append(KeyValue(key=f"{what}_cpu_seconds_total", value=diagnostic_value(seconds)))
        # the exact pose covariance's cost, on the output thread (README, pose)
        status.values.append(KeyValue(key="pose_cov_exact_cpu_seconds_total", value=diagnostic_value(self._poses.exact_seconds)))
        if self._tf is not None:  # transforms not sent: a stamp already sent, no odometry at the stamp (README, TF)
            status.values.append(KeyValue(key="tf_sent", value=str(self._tf.n_sent)))
            status.values.append(KeyValue(key="tf_repeated_stamp", value=str(self._tf.n_repeated)))
            status.values.append(KeyValue(key="tf_no_odometry", value=str(self._tf.n_no_odometry)))
            status.values.append(KeyValue(key="tf_resent", value=str(self._tf.n_resent)))
        self.pub_diag.publish(DiagnosticArray(header=status_header(self), status=[status]))


class _Receiver:
    """An inbound subscription's callback, which knows its subscription.

    After the message it is given it takes up to :data:`DRAIN_MAX` more from the same
    subscription's queue, in order, as the executor would have handed them over; then ``flush``
    publishes what the submaps' joins held back (:data:`POSE_COALESCE_S`).
    """

    def __init__(
        self, receive: Callable[[str, bytes, str], None], flush: Callable[[], None], topic: str, robot: str,
        ok: Callable[[], bool],
    ) -> None:
        self._receive, self._flush, self.topic, self.robot, self._ok = receive, flush, topic, robot, ok
        self.subscription: Subscription | None = None

    def __call__(self, raw: bytes) -> None:
        try:
            self._receive(self.topic, raw, self.robot)
            for _ in range(DRAIN_MAX):
                if not self._ok():  # shut down (SIGINT, SIGTERM): the rest of the queue is not taken
                    return
                queued = take_queued(self.subscription)
                if queued is None:
                    return
                self._receive(self.topic, queued, self.robot)
        finally:
            self._flush()


def take_queued(subscription: Subscription | None) -> Any | None:
    """Take the next message waiting in ``subscription``'s queue (raw bytes for a raw one), or None.

    This is the executor's own take (``rclpy.executors``, ``rclpy.wait_for_message``); a
    destroyed subscription has nothing to take.
    """
    if subscription is None:
        return None
    try:
        with subscription.handle:
            taken = subscription.handle.take_message(subscription.msg_type, subscription.raw)
    except InvalidHandle:
        return None
    return None if taken is None else taken[0]


def _decode(topic: str, raw: bytes, limits: InputLimits) -> tuple[LocalMap, int, Stamp]:
    """Decode the raw CDR of a ``local_map`` or ``pose_graph`` message into a local map, its sequence number and stamp.

    Sizes beyond ``limits`` are refused from the message's layout before anything is allocated;
    the numbers are checked by the validation of the decoded map or graph and of the chunk's map.

    Raises:
        MessageError: the bytes are not a Float64MultiArray, it does not follow the layout, a
            size is above its limit, or a ``local_map`` message carries a global map.
        LinearSlamError: the map or pose graph it carries is invalid (a numeric limit included).
    """
    try:
        msg = deserialize_message(raw, Float64MultiArray)
    except Exception as exc:  # rclpy raises plain exceptions for bad CDR
        raise MessageError(f"not a serialized std_msgs/Float64MultiArray ({type(exc).__name__}: {exc})") from None
    if topic.endswith("pose_graph"):
        chunk = decode_chunk(*parts(msg), limits=limits)
        return chunk_to_local_map(chunk.graph, limits), chunk.seq, chunk.stamp
    decoded = decode_map(*parts(msg), limits=limits)
    return submap_of(decoded), decoded.seq, decoded.stamp


def diagnostic_value(value: float) -> str:
    """A statistic as ``/diagnostics`` shows it: counts in full (``%g`` rounded 1234570 to 1.23457e+06), other
    figures to 10 significant digits."""
    if math.isfinite(value) and value == int(value) and abs(value) < 2**53:
        return str(int(value))
    return f"{value:.10g}"


def _key(robot: str, seq: int) -> Any:
    """The key of a submap's per-sequence records: its number, with its robot when it has one."""
    return (robot, seq) if robot else seq


def _robot_seq(key: Any) -> tuple[str, int]:
    """Inverse of :func:`_key`."""
    return key if isinstance(key, tuple) else ("", key)


def status_header(node: Node) -> Any:
    """Return a header stamped with the node's clock."""
    from std_msgs.msg import Header

    return Header(stamp=node.get_clock().now().to_msg())


def _usage() -> str:
    """The joiner's parameters with their defaults, whether they are read-only, and what they do."""
    lines = ["Joins every submap on local_map / pose_graph as it arrives and publishes global_map (README.md).", "",
             "parameters (default; * read-only):"]
    for d in (*parameter_declarations(), *TF_PARAMETERS):
        lines.append(f"  {d.name} = {d.default!r}{' *' if d.spec.read_only else ''}: {d.spec.description}")
    return "\n".join(lines)


def main(args: list[str] | None = None) -> None:
    """Start the joiner; Ctrl-C stops it cleanly; an invalid parameter exits with code 2; ``--help`` lists the parameters."""
    if print_usage_if_asked(args, NODE_NAME, _usage()):
        return
    profile = inbound_dds_profile(os.environ, share_directory())
    if profile is not None:  # read by FastDDS when rclpy creates the participant
        os.environ[PROFILE_VARIABLES[0]] = str(profile)
    rclpy.init(args=args)
    node = None
    try:
        node = JoinerNode()
        # What exists now (modules, rclpy, the node) lives as long as the process: the cyclic
        # collector stops rescanning it (README, "Scale": its full collections held the
        # interpreter lock for 50-60 ms while the outputs built their messages).
        gc.freeze()
        executor = SingleThreadedExecutor()  # outputs have their own thread (PeriodicThread)
        executor.add_node(node)
        executor.spin()
    except (ConfigError, SnapshotError, JournalError) as exc:  # at start-up, or a journal that failed since (disk full)
        rclpy.logging.get_logger(NODE_NAME).fatal(f"{'cannot start' if node is None else 'stopped'}: {exc}")
        rclpy.try_shutdown()
        sys.exit(2)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except Exception:
        # SIGINT / SIGTERM shut the context down while a callback was still draining its queue: its next
        # publication raises rclpy's RCLError ("publisher's context is invalid"), a normal stop all the same
        if node is None or node.context.ok():
            raise
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()


if __name__ == "__main__":  # pragma: no cover
    main()
