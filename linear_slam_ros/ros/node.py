"""The ``joiner`` ROS 2 node: subscriptions, parameters, publishing; the joining is in the core.

Run with ``ros2 run linear_slam_ros joiner --ros-args --params-file config/joiner.yaml``.
Topics, services and parameters are tabulated in the README.
"""

from __future__ import annotations

import dataclasses
import enum
import sys
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
from std_msgs.msg import Float64MultiArray
from std_srvs.srv import Trigger
from visualization_msgs.msg import MarkerArray

from linear_slam_ros.core.errors import ConfigError, LinearSlamError
from linear_slam_ros.core.runtime import set_blas_threads, tune_allocator
from linear_slam_ros.io.results import write_map
from linear_slam_ros.joiner.config import JoinerConfig, OutputFrame, ParameterDeclaration, parameter_declarations
from linear_slam_ros.joiner.joiner import Joiner, JoinerState, global_result
from linear_slam_ros.joiner.registry import get_strategy
from linear_slam_ros.pose_graph.chunks import chunk_to_local_map
from linear_slam_ros.ros.qos import inbound_qos, latched_qos
from msg_adapters import Encoded, Stamp, decode_chunk, decode_map
from msg_adapters.global_map import encode_global
from msg_adapters.ros import parts, to_msg
from msg_adapters.views import map_views

NODE_NAME = "joiner"
PUBLISH_DUTY = 0.25
"""Largest fraction of wall time spent computing outputs (the rest is left to joining)."""



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
        for decl in parameter_declarations():
            self.declare_parameter(decl.name, decl.default, _descriptor(decl))
        # Raises ConfigError, naming the parameter, its value and the allowed values: main() exits with 2.
        config = JoinerConfig.from_mapping({d.name: self.get_parameter(d.name).value for d in parameter_declarations()})
        self.config = config
        self.add_on_set_parameters_callback(self._on_set_parameters)
        tune_allocator()
        set_blas_threads(get_strategy(config.mode, config.map_type).blas_threads)

        self.joiner = Joiner(config.mode, config.map_type, reorder_window=config.reorder_window)
        self.joiner.on_reject = lambda reason, message: self.get_logger().warning(message)
        self.n_received = 0
        self._version = 0  # bumped on every state change; the publisher compares it
        self._published_version = -1
        self._lock = threading.Lock()  # guards (joiner.state, _version) snapshots
        self._next_publish = 0.0

        depth = config.queue_depth
        inbound, latched = inbound_qos(depth), latched_qos()
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
        self._timer = self.create_timer(1.0 / config.publish_rate, self._on_publish_timer, callback_group=output_group)
        self.create_timer(config.summary_period, self._on_summary_timer, callback_group=output_group)
        self.get_logger().info(
            f"joiner ready: mode={config.mode.value}, map_type={config.map_type.value}, "
            f"output_frame={config.output_frame.value}, map_frame={config.map_frame}, queue_depth={depth or 'keep all'}"
        )

    # ------------------------------------------------------------------ parameters

    def _on_set_parameters(self, params: list[Parameter]) -> SetParametersResult:
        try:
            changed = JoinerConfig.from_mapping({**self._config_values(), **{p.name: p.value for p in params}})
        except ConfigError as exc:
            return SetParametersResult(successful=False, reason=str(exc))
        self.config = changed
        for p in params:
            if p.name == "publish_rate":
                self._timer.timer_period_ns = int(1e9 / float(p.value))
            if p.name == "reorder_window":
                self.joiner.reorder_window = int(p.value)
        return SetParametersResult(successful=True)

    def _config_values(self) -> dict[str, Any]:
        """Return the current configuration as parameter values (enums as strings)."""
        return {
            k: v.value if isinstance(v, enum.Enum) else v for k, v in dataclasses.asdict(self.config).items()
        }

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
            decoded = decode_chunk(*parts(msg))
            submap = chunk_to_local_map(decoded.graph)
        except LinearSlamError as exc:
            self.joiner.reject("bad_message", f"pose_graph rejected: {exc}")
            return
        self._offer(submap, decoded.seq)

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
        folder = Path(self.config.save_directory)
        try:
            joined = global_result(state, OutputFrame.FIRST_POSE)
            if joined is None:
                response.success, response.message = False, "nothing to save: no submap joined yet"
                return response
            write_map(joined, folder, state.first_pose_id)
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

    def _encode(self, joined: Any, state: JoinerState, stats: dict[str, float]) -> Encoded:
        return encode_global(joined, state.last_seq or 0, self._stamp(), state.n_joined, stats)

    def _publish(self, state: JoinerState, stats: dict[str, float]) -> None:
        config = self.config
        joined = global_result(state, config.output_frame)
        if joined is None:  # feature-only: no group defines a feature frame yet
            return
        self.pub_global.publish(to_msg(self._encode(joined, state, stats)))
        stamp = self.get_clock().now().to_msg()
        views = map_views(joined, state.first_pose_id, config.map_frame, stamp, config.ellipse_max_state)
        if views.path is not None:
            self.pub_path.publish(views.path)
        self.pub_markers.publish(views.markers)
        if views.pose is not None:
            self.pub_pose.publish(views.pose)

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
    """Start the joiner; Ctrl-C stops it cleanly; an invalid parameter exits with code 2."""
    rclpy.init(args=args)
    node = None
    try:
        node = JoinerNode()
        executor = MultiThreadedExecutor(num_threads=2)
        executor.add_node(node)
        executor.spin()
    except ConfigError as exc:
        rclpy.logging.get_logger(NODE_NAME).fatal(f"invalid configuration: {exc}")
        rclpy.try_shutdown()
        sys.exit(2)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()


if __name__ == "__main__":  # pragma: no cover
    main()
