"""The joiner's optional TF output: ``map_frame`` -> ``odom_frame`` (or ``base_frame``) at the newest pose (``publish_tf``).

With ``publish_tf`` true the node broadcasts the newest pose as a transform, where it publishes
``pose``. With ``odom_frame`` set (REP-105: odometry owns ``odom_frame`` -> ``base_frame``) it
sends ``map_frame`` -> ``odom_frame``, the map pose composed with the inverse of the odometry
transform at the pose's stamp (looked up in a ``tf2_ros.Buffer``, without waiting: when the
odometry has no transform at that stamp yet, that pose's transform is not sent, and a throttled
warning says why); with ``odom_frame`` empty it sends ``map_frame`` -> ``base_frame`` (a
front-end that publishes no odometry TF). One transform per child frame and stamp: a better pose
of an instant already sent (the global map's, after the arrival's) goes on ``pose`` only, since
TF listeners treat a repeated stamp as a publisher error (``TF_REPEATED_DATA``) or keep both.
How it is sent depends on what is installed:

- ``tf2_ros`` (every ROS 2 Jazzy install): its ``TransformBroadcaster`` (topic ``/tf``).
- ``tf2_msgs`` without ``tf2_ros``: a ``tf2_msgs/TFMessage`` publisher on ``/tf`` with the
  broadcaster's QoS (reliable, volatile, depth 100), which is what the broadcaster does.
- neither (the PyPI Jazzy wheels: they ship no tf2 package at all): one warning at start-up,
  and no TF. ``odom_frame`` needs ``tf2_ros`` (its buffer): without it, the same warning.

These parameters belong to the node's ROS outputs, not to the joining configuration
(:class:`~linear_slam_ros.joiner.config.JoinerConfig`), so they are declared here.
"""

from __future__ import annotations

import importlib
import threading
from collections.abc import Callable
from typing import Any

import numpy as np
from builtin_interfaces.msg import Time
from geometry_msgs.msg import Quaternion, Transform, TransformStamped, Vector3
from rclpy.node import Node
from rclpy.qos import QoSProfile
from scipy.spatial.transform import Rotation

from linear_slam_ros.joiner.config import ParameterDeclaration, ParamSpec

REMEMBERED_STAMPS = 256
"""Stamps of ``map -> odom`` that :meth:`TfOutput.resend` keeps clear of (tf2's buffer holds 10 s: at the default
20 re-sends a second this covers about 12 s)."""

TF_QOS_DEPTH = 100
"""History depth of the ``/tf`` publisher (``tf2_ros.TransformBroadcaster``'s default)."""

TF_PARAMETERS = (
    ParameterDeclaration(
        "publish_tf",
        False,
        ParamSpec(
            "broadcast the transform map_frame -> base_frame of the newest pose on /tf (needs tf2_ros or tf2_msgs)",
            read_only=True,
        ),
        (),
    ),
    ParameterDeclaration(
        "base_frame",
        "base_link",
        ParamSpec(
            "the robot's frame at the newest pose: child of the publish_tf transform when odom_frame is empty",
            read_only=True,
        ),
        (),
    ),
    ParameterDeclaration(
        "odom_frame",
        "",
        ParamSpec(
            "with publish_tf: send map_frame -> odom_frame, composed with the odometry's odom_frame -> base_frame at the "
            "pose's stamp (REP-105; needs tf2_ros); empty: send map_frame -> base_frame",
            read_only=True,
        ),
        (),
    ),
    ParameterDeclaration(
        "tf_publish_period",
        0.05,
        ParamSpec(
            "with publish_tf and odom_frame: seconds between re-sends of the newest map_frame -> odom_frame, each "
            "stamped this far ahead of the node's clock, so that lookups at the current time never extrapolate "
            "between submaps; 0: sent with each pose only",
            read_only=True, bounds=(0.0, 10.0),
        ),
        (),
    ),
)
"""The node's TF parameters, declared beside :func:`~linear_slam_ros.joiner.config.parameter_declarations`."""

TfSender = Callable[[TransformStamped], None]
OdomLookup = Callable[[str, str, Time], TransformStamped]
"""``lookup(odom_frame, base_frame, stamp)``: the pose of ``base_frame`` in ``odom_frame`` at ``stamp``
(``tf2_ros.Buffer.lookup_transform`` without waiting); raises when it has none."""


def map_to_odom(map_base: TransformStamped, odom_base: TransformStamped) -> TransformStamped:
    """Return ``map -> odom`` from ``map -> base`` and the odometry's ``odom -> base`` (same base frame).

    ``T_map_odom = T_map_base · T_odom_base⁻¹``: rotation ``R_mb R_obᵀ``, translation
    ``t_mb - R_mo t_ob``. The result has ``map_base``'s header and ``odom_base``'s parent frame as
    child.
    """
    r_mb, t_mb = _rotation_translation(map_base.transform)
    r_ob, t_ob = _rotation_translation(odom_base.transform)
    r_mo = r_mb * r_ob.inv()
    t_mo = t_mb - r_mo.apply(t_ob)
    qx, qy, qz, qw = (float(v) for v in r_mo.as_quat(canonical=True))
    transform = Transform(
        translation=Vector3(x=float(t_mo[0]), y=float(t_mo[1]), z=float(t_mo[2])),
        rotation=Quaternion(x=qx, y=qy, z=qz, w=qw),
    )
    return TransformStamped(header=map_base.header, child_frame_id=odom_base.header.frame_id, transform=transform)


def _rotation_translation(transform: Transform) -> tuple[Rotation, np.ndarray]:
    q, t = transform.rotation, transform.translation
    return Rotation.from_quat([q.x, q.y, q.z, q.w]), np.array([t.x, t.y, t.z])


class TfOutput:
    """Sends each newest pose's transform once per child frame and stamp, through ``odom_frame`` when set.

    Thread-safe: the node sends from its executor (arrivals) and its output thread (global maps).

    Args:
        send: broadcasts a transform (:func:`tf_sender`).
        odom_frame: REP-105's odometry frame; empty: the pose goes out as ``map -> base``.
        lookup: the odometry transform (needed with ``odom_frame``).
        warn: logs why a transform was not sent (the node throttles it).
    """

    def __init__(
        self, send: TfSender, odom_frame: str = "", lookup: OdomLookup | None = None,
        warn: Callable[[str], None] | None = None,
    ) -> None:
        if odom_frame and lookup is None:
            raise ValueError(f"odom_frame {odom_frame!r} needs an odometry lookup (tf2_ros)")
        self._send, self._odom_frame, self._lookup, self._warn = send, odom_frame, lookup, warn
        self._lock = threading.Lock()
        self._last: dict[str, tuple[int, int]] = {}  # child frame -> newest stamp sent
        self._map_odom: TransformStamped | None = None  # the newest map -> odom sent, for resend()
        self._odom_stamps: set[tuple[int, int]] = set()  # stamps map -> odom went out at (resend() avoids them)
        self._resent_at: tuple[int, int] | None = None  # the last stamp resend() sent
        self.n_sent = 0
        self.n_resent = 0  # map -> odom sent again by resend()
        self.n_repeated = 0  # transforms of a stamp already sent (not sent)
        self.n_no_odometry = 0  # odometry lookups that failed (not sent)

    def publish(self, map_base: TransformStamped) -> bool:
        """Send ``map -> base`` (or ``map -> odom``) unless a transform of this child frame at this
        stamp or a newer one went out; return whether it was sent."""
        stamp = (map_base.header.stamp.sec, map_base.header.stamp.nanosec)
        child = map_base.child_frame_id
        with self._lock:
            if child in self._last and stamp <= self._last[child]:
                self.n_repeated += 1
                return False
            transform = map_base
            if self._lookup is not None:
                try:
                    odom_base = self._lookup(self._odom_frame, child, map_base.header.stamp)
                except Exception as exc:  # tf2's Lookup/Extrapolation/Connectivity exceptions share no base class we import
                    self.n_no_odometry += 1
                    if self._warn is not None:
                        self._warn(f"no TF sent at {stamp[0]}.{stamp[1]:09d}: no {self._odom_frame} -> {child} there ({exc})")
                    return False
                transform = map_to_odom(map_base, odom_base)
                self._map_odom = transform
                self._remember(stamp)
            self._last[child] = stamp
            self.n_sent += 1
        self._send(transform)
        return True

    def resend(self, stamp: Time, parent_frame: str | None = None) -> bool:
        """Send the newest ``map -> odom`` again at ``stamp``; return whether it was.

        ``map -> odom`` changes only when a submap is joined, while the odometry's ``odom -> base``
        goes on: without a recent ``map -> odom``, a lookup of ``map -> base`` at the current time
        extrapolates and fails. So the node re-sends it ahead of its clock, as SLAM nodes do. Only
        with ``odom_frame``: ``map -> base`` sent again would say the robot stood still.

        Not at a stamp ``map -> odom`` already went out at (a stopped sim clock, a pose's own stamp):
        tf2 takes a repeated stamp as a publisher error. A clock that went back (a bag played again)
        is followed. A pose's transform at a stamp a re-send already used still goes out (the
        correction matters more; tf2 may then warn ``TF_REPEATED_DATA`` once).

        Args:
            stamp: the stamp to send it at.
            parent_frame: the parent to send it under (the node's current ``map_frame``); ``None``:
                the one it was sent with.
        """
        key = (stamp.sec, stamp.nanosec)
        with self._lock:
            if self._map_odom is None or key == self._resent_at or key in self._odom_stamps:
                return False
            previous = self._map_odom
            transform = TransformStamped(child_frame_id=previous.child_frame_id, transform=previous.transform)
            transform.header.frame_id = parent_frame or previous.header.frame_id
            transform.header.stamp = stamp
            self._resent_at = key
            self._remember(key)
            self.n_resent += 1
        self._send(transform)
        return True

    def _remember(self, key: tuple[int, int]) -> None:
        """Note a stamp ``map -> odom`` went out at (the newest :data:`REMEMBERED_STAMPS`)."""
        self._odom_stamps.add(key)
        if len(self._odom_stamps) > REMEMBERED_STAMPS:
            self._odom_stamps.discard(min(self._odom_stamps))

    def reset(self) -> None:
        """Forget the stamps and the ``map -> odom`` sent (``~/reset``, ``~/load_map``: a new map may start at an
        earlier time, and its first pose has not been sent)."""
        with self._lock:
            self._last.clear()
            self._map_odom = None
            self._odom_stamps.clear()
            self._resent_at = None


def tf_sender(node: Node) -> tuple[TfSender | None, str]:
    """Return a function that broadcasts a transform from ``node``, and what it uses.

    Returns:
        ``(send, "tf2_ros")``, ``(send, "tf2_msgs")`` or ``(None, reason)`` when neither
        package can be imported (``reason`` names both).
    """
    try:  # imported by name: optional packages (neither is on PyPI), so no static import for mypy to miss
        tf2_ros = importlib.import_module("tf2_ros")
    except ImportError:
        pass
    else:
        broadcaster = tf2_ros.TransformBroadcaster(node)
        return broadcaster.sendTransform, "tf2_ros"
    message_class = tf_message_class()
    if message_class is None:
        return None, "neither tf2_ros nor tf2_msgs can be imported (the PyPI Jazzy wheels have no tf2 package)"
    publisher = node.create_publisher(message_class, "/tf", QoSProfile(depth=TF_QOS_DEPTH))

    def send(transform: TransformStamped) -> None:
        publisher.publish(message_class(transforms=[transform]))

    return send, "tf2_msgs"


class _OdomBuffer:
    """A ``tf2_ros`` buffer filled by its listener, looked up without waiting.

    The listener gets a node of its own (``node=None``), spun on its own thread: given the joiner's
    node with ``spin_thread``, it would add that node to a second executor, which takes it from the
    joiner's; and on the joiner's executor, ``/tf`` at odometry rates would queue with the submaps.
    """

    def __init__(self, tf2_ros: Any) -> None:
        self.buffer = tf2_ros.Buffer()
        self.listener = tf2_ros.TransformListener(self.buffer, None, spin_thread=True)

    def __call__(self, odom_frame: str, base_frame: str, stamp: Time) -> TransformStamped:
        from rclpy.duration import Duration
        from rclpy.time import Time as RclpyTime

        transform: TransformStamped = self.buffer.lookup_transform(
            odom_frame, base_frame, RclpyTime.from_msg(stamp), timeout=Duration(seconds=0)
        )
        return transform


def odom_lookup() -> tuple[OdomLookup | None, str]:
    """Return the odometry lookup of ``odom_frame`` (a ``tf2_ros`` buffer and its listener), and what it uses.

    Returns:
        ``(lookup, "tf2_ros buffer")``, or ``(None, reason)`` when ``tf2_ros`` cannot be imported.
    """
    try:
        tf2_ros = importlib.import_module("tf2_ros")
    except ImportError:
        return None, "odom_frame needs tf2_ros (its buffer), which cannot be imported"
    return _OdomBuffer(tf2_ros), "tf2_ros buffer"


def tf_message_class() -> Any | None:
    """Return ``tf2_msgs.msg.TFMessage``, or ``None`` when it is not installed (for a subscriber on ``/tf``)."""
    try:
        return importlib.import_module("tf2_msgs.msg").TFMessage
    except ImportError:
        return None
