"""The ``joiner`` ROS 2 node: subscriptions, parameters, publishing; the joining is in the core.

Run with ``ros2 run linear_slam_ros joiner --ros-args --params-file config/joiner.yaml``.
Topics, services and parameters are tabulated in the README.
"""

from __future__ import annotations

import threading
import time
from pathlib import Path
from typing import Any

import rclpy
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import PoseStamped
from nav_msgs.msg import Path as PathMsg
from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor, SetParametersResult
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.executors import ExternalShutdownException, MultiThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from std_msgs.msg import Float64MultiArray
from std_srvs.srv import Trigger
from visualization_msgs.msg import MarkerArray

from linear_slam_ros.cli.main import write_feature_result, write_result
from linear_slam_ros.core.errors import LinearSlamError
from linear_slam_ros.feature_only.maps import FeatureMap
from linear_slam_ros.core.frames import change_frame
from linear_slam_ros.joiner.joiner import OUTPUT_FRAMES, Joiner, JoinerState, global_feature_map_of, global_map_of
from linear_slam_ros.core.local_map import LocalMap
from linear_slam_ros.pose_graph.chunks import chunk_to_local_map
from linear_slam_ros.evaluation.runner import JoinMethod, MapType
from linear_slam_ros.core.runtime import blas_threads_for, set_blas_threads, tune_allocator
from msg_adapters import MAP_KIND_GLOBAL, Encoded, Stamp, decode_chunk, decode_map, encode_feature_map, encode_map
from msg_adapters.ros import parts, to_msg
from msg_adapters.views import (
    current_pose_msg, feature_covariances, feature_map_covariances, feature_markers, path_msg, point_markers,
)

NODE_NAME = "joiner"
PUBLISH_DUTY = 0.25
"""Largest fraction of wall time spent computing outputs (the rest is left to joining)."""

# name: (default, description, read_only, range)
PARAMETERS: dict[str, tuple[Any, str, bool, tuple[float, float] | None]] = {
    "mode": ("sequential", "joining method: 'sequential' (exact, robocentric end-pose frame) or 'online-dc' "
             "(online divide and conquer, for long streams)", True, None),
    "map_type": ("as-is", "'as-is' joins the submaps' variables; 'feature-only' marginalises the poses of "
                 "pose-feature submaps and joins feature-only maps in feature-defined frames (D-SLAM)", True, None),
    "output_frame": ("end_pose", "frame of the global_map message: 'end_pose' (robocentric, newest end pose) "
                     "or 'first_pose'", False, None),
    "publish_rate": (2.0, "maximum rate of the output topics, Hz", False, (0.05, 100.0)),
    "map_frame": ("map", "frame_id of the viewing topics (the first pose's frame)", False, None),
    "queue_depth": (0, "subscription history depth; 0 keeps all (reliable, no submap dropped)", True, (0, 1_000_000)),
    "reorder_window": (100, "early submaps held while waiting for a missing sequence number", False, (1, 1_000_000)),
    "ellipse_max_state": (1500, "largest global state (scalars) for which feature covariance ellipses are drawn",
                          False, (0, 1_000_000)),
    "summary_period": (5.0, "seconds between info-level summary lines and /diagnostics", False, (0.1, 3600.0)),
    "save_directory": ("saved_map", "folder where ~/save_map writes poses.txt, features.txt and a bag", False, None),
}


def _descriptor(name: str, description: str, read_only: bool, bounds: tuple[float, float] | None, default: Any) -> ParameterDescriptor:
    desc = ParameterDescriptor(name=name, description=description, read_only=read_only)
    if bounds is not None and isinstance(default, int) and not isinstance(default, bool):
        desc.integer_range = [IntegerRange(from_value=int(bounds[0]), to_value=int(bounds[1]), step=1)]
    elif bounds is not None:
        desc.floating_point_range = [FloatingPointRange(from_value=float(bounds[0]), to_value=float(bounds[1]), step=0.0)]
    return desc


class JoinerNode(Node):
    """Joins every submap as it arrives and republishes the global map and views."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__(NODE_NAME, **kwargs)
        for name, (default, description, read_only, bounds) in PARAMETERS.items():
            self.declare_parameter(name, default, _descriptor(name, description, read_only, bounds, default))
        mode = self.get_parameter("mode").value
        if mode not in (JoinMethod.SEQUENTIAL.value, JoinMethod.ONLINE_DC.value):
            self.get_logger().error(f"parameter mode={mode!r} is not 'sequential' or 'online-dc'; using 'sequential'")
            mode = JoinMethod.SEQUENTIAL.value
        map_type = self.get_parameter("map_type").value
        if map_type not in [t.value for t in MapType]:
            self.get_logger().error(f"parameter map_type={map_type!r} is not 'as-is' or 'feature-only'; using 'as-is'")
            map_type = MapType.AS_IS.value
        if self.get_parameter("output_frame").value not in OUTPUT_FRAMES:
            self.get_logger().error(f"parameter output_frame must be one of {OUTPUT_FRAMES}; using 'end_pose'")
            self.set_parameters([Parameter("output_frame", value="end_pose")])
        self.add_on_set_parameters_callback(self._on_set_parameters)
        tune_allocator()
        set_blas_threads(blas_threads_for(mode))

        self.joiner = Joiner(JoinMethod(mode), MapType(map_type), reorder_window=int(self.get_parameter("reorder_window").value))
        self.joiner.on_reject = lambda reason, message: self.get_logger().warning(message)
        self.n_received = 0
        self._version = 0  # bumped on every state change; the publisher compares it
        self._published_version = -1
        self._lock = threading.Lock()  # guards (joiner.state, _version) snapshots
        self._next_publish = 0.0

        depth = int(self.get_parameter("queue_depth").value)
        inbound = QoSProfile(
            history=HistoryPolicy.KEEP_ALL if depth == 0 else HistoryPolicy.KEEP_LAST,
            depth=max(depth, 1),
            reliability=ReliabilityPolicy.RELIABLE,
            durability=DurabilityPolicy.VOLATILE,
        )
        latched = QoSProfile(
            history=HistoryPolicy.KEEP_LAST, depth=1, reliability=ReliabilityPolicy.RELIABLE,
            durability=DurabilityPolicy.TRANSIENT_LOCAL,
        )
        joining_group = MutuallyExclusiveCallbackGroup()
        output_group = MutuallyExclusiveCallbackGroup()
        self.create_subscription(Float64MultiArray, "local_map", self._on_local_map, inbound, callback_group=joining_group)
        self.create_subscription(Float64MultiArray, "pose_graph", self._on_pose_graph, inbound, callback_group=joining_group)
        self.pub_global = self.create_publisher(Float64MultiArray, "global_map", latched)
        self.pub_path = self.create_publisher(PathMsg, "path", latched)
        self.pub_markers = self.create_publisher(MarkerArray, "features", latched)
        self.pub_pose = self.create_publisher(PoseStamped, "pose", latched)
        self.pub_diag = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        self.create_service(Trigger, "~/reset", self._on_reset, callback_group=joining_group)
        self.create_service(Trigger, "~/save_map", self._on_save_map, callback_group=output_group)
        self._timer = self.create_timer(1.0 / float(self.get_parameter("publish_rate").value), self._on_publish_timer, callback_group=output_group)
        self.create_timer(float(self.get_parameter("summary_period").value), self._on_summary_timer, callback_group=output_group)
        self.get_logger().info(
            f"joiner ready: mode={mode}, map_type={map_type}, output_frame={self.get_parameter('output_frame').value}, "
            f"map_frame={self.get_parameter('map_frame').value}, queue_depth={depth or 'keep all'}"
        )

    # ------------------------------------------------------------------ parameters

    def _on_set_parameters(self, params: list[Parameter]) -> SetParametersResult:
        for p in params:
            if p.name == "output_frame" and p.value not in OUTPUT_FRAMES:
                return SetParametersResult(successful=False, reason=f"output_frame must be one of {OUTPUT_FRAMES}, got {p.value!r}")
            if p.name == "publish_rate":
                self._timer.timer_period_ns = int(1e9 / float(p.value))
            if p.name == "reorder_window":
                self.joiner.reorder_window = int(p.value)
        return SetParametersResult(successful=True)

    # ------------------------------------------------------------------ inputs

    def _on_local_map(self, msg: Float64MultiArray) -> None:
        self.n_received += 1
        try:
            decoded = decode_map(*parts(msg))
        except LinearSlamError as exc:
            self.joiner.reject("bad_message", f"local_map rejected: {exc}")
            return
        self._offer(decoded.local_map, decoded.seq)

    def _on_pose_graph(self, msg: Float64MultiArray) -> None:
        self.n_received += 1
        try:
            chunk = decode_chunk(*parts(msg)).chunk
            submap = chunk_to_local_map(chunk)
        except LinearSlamError as exc:
            self.joiner.reject("bad_message", f"pose_graph rejected: {exc}")
            return
        self._offer(submap, chunk.seq)

    def _offer(self, submap: Any, seq: int) -> None:
        with self._lock:
            joined = self.joiner.offer(submap, seq)
            if joined:
                self._version += 1
        for s in joined:
            self.get_logger().debug(
                f"joined submap seq {s}: {self.joiner.state.n_joined} joined, last join "
                f"{self.joiner.join_seconds[-1] * 1e3:.2f} ms"
            )

    # ------------------------------------------------------------------ services

    def _on_reset(self, _request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        with self._lock:
            self.joiner.reset()
            self.n_received = 0
            self._version += 1
        response.success, response.message = True, "global map cleared"
        self.get_logger().info("global map reset")
        return response

    def _on_save_map(self, _request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        with self._lock:
            state = self.joiner.state
        folder = Path(str(self.get_parameter("save_directory").value))
        try:
            joined = self._global(state, "first_pose")
            if joined is None:
                response.success, response.message = False, "nothing to save: no submap joined yet"
                return response
            if isinstance(joined, FeatureMap):
                write_feature_result(folder, joined)
            else:
                write_result(folder, joined, joined.frame_id)
            from linear_slam_ros.ros.bagio import write_messages

            encoded = self._encode(joined, state, self.joiner.stats())
            write_messages(folder / "global_map_bag", [("global_map", 0, encoded)], latched={"global_map"}, overwrite=True)
        except (LinearSlamError, OSError) as exc:
            response.success, response.message = False, f"save failed: {exc}"
            return response
        response.success, response.message = True, f"saved {state.n_joined} submaps to {folder}"
        return response

    # ------------------------------------------------------------------ outputs

    def _stamp(self) -> Stamp:
        now = self.get_clock().now().to_msg()
        return Stamp(int(now.sec), int(now.nanosec))

    def _on_publish_timer(self) -> None:
        now = time.monotonic()
        if now < self._next_publish:
            return
        with self._lock:
            state, version, stats = self.joiner.state, self._version, self.joiner.stats()
        if version == self._published_version or state.n_joined == 0:
            return
        try:
            self._publish(state, stats)
        except LinearSlamError as exc:  # pragma: no cover - outputs of a valid state
            self.get_logger().error(f"could not publish the global map: {exc}")
        self._published_version = version
        # Outputs of a large map cost CPU the joining thread needs: keep publishing under
        # PUBLISH_DUTY of the time, whatever publish_rate asks for.
        self._next_publish = now + (time.monotonic() - now) / PUBLISH_DUTY

    @staticmethod
    def _global(state: JoinerState, output_frame: str) -> LocalMap | FeatureMap | None:
        """Return the global map (``None`` while there is none)."""
        if state.map_type is MapType.FEATURE_ONLY:
            return global_feature_map_of(state)
        return global_map_of(state, output_frame)

    def _encode(self, joined: LocalMap | FeatureMap, state: JoinerState, stats: dict[str, float]) -> Encoded:
        args = (state.last_seq or 0, self._stamp(), MAP_KIND_GLOBAL, state.n_joined, stats)
        return encode_feature_map(joined, *args) if isinstance(joined, FeatureMap) else encode_map(joined, *args)

    def _publish(self, state: JoinerState, stats: dict[str, float]) -> None:
        joined = self._global(state, str(self.get_parameter("output_frame").value))
        if joined is None:  # feature-only: no group defines a feature frame yet
            return
        self.pub_global.publish(to_msg(self._encode(joined, state, stats)))
        ros_stamp = self.get_clock().now().to_msg()
        map_frame = str(self.get_parameter("map_frame").value)
        max_state = int(self.get_parameter("ellipse_max_state").value)
        if isinstance(joined, FeatureMap):  # no poses: features only, in the feature frame
            covs = feature_map_covariances(joined, max_state)
            self.pub_markers.publish(point_markers(joined.dim, joined.positions(), map_frame, ros_stamp, covs))
            return
        first = state.first_pose_id
        assert first is not None
        in_first = joined if joined.frame_id == first else change_frame(joined, first)
        self.pub_path.publish(path_msg(in_first, map_frame, ros_stamp))
        covs = feature_covariances(in_first, max_state)
        self.pub_markers.publish(feature_markers(in_first, map_frame, ros_stamp, covs))
        if joined.end_id is not None:
            self.pub_pose.publish(current_pose_msg(in_first, joined.end_id, map_frame, ros_stamp))

    def _on_summary_timer(self) -> None:
        with self._lock:
            stats, state = self.joiner.stats(), self.joiner.state
            rejected = dict(self.joiner.rejected)
        self.get_logger().info(
            f"{int(stats['n_joined'])} submaps joined, {int(stats['n_rejected'])} rejected {rejected or ''}, "
            f"last join {stats['last_join_ms']:.2f} ms"
        )
        status = DiagnosticStatus(level=DiagnosticStatus.OK, name=f"{self.get_name()}: joining", hardware_id=self.get_name())
        status.message = "joining" if state.n_joined else "waiting for submaps"
        if stats["n_rejected"]:
            status.level, status.message = DiagnosticStatus.WARN, f"{int(stats['n_rejected'])} submaps rejected"
        status.values = [KeyValue(key=k, value=f"{v:g}") for k, v in stats.items()]
        status.values.append(KeyValue(key="n_received", value=str(self.n_received)))
        self.pub_diag.publish(DiagnosticArray(header=status_header(self), status=[status]))


def status_header(node: Node) -> Any:
    """Return a header stamped with the node's clock."""
    from std_msgs.msg import Header

    return Header(stamp=node.get_clock().now().to_msg())


def main(args: list[str] | None = None) -> None:
    """Start the joiner; Ctrl-C stops it cleanly."""
    rclpy.init(args=args)
    node = None
    try:
        node = JoinerNode()
        executor = MultiThreadedExecutor(num_threads=2)
        executor.add_node(node)
        executor.spin()
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()


if __name__ == "__main__":  # pragma: no cover
    main()
