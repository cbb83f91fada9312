"""The QoS profiles of linear_slam_ros's topics, in one place.

Every profile is reliable: a lost submap changes the joined map, and a lost global map would
leave a subscriber with a stale one. Each function returns a new :class:`QoSProfile`, so a
caller that adjusts its copy changes nobody else's.

- :func:`latched_qos`: the joiner's outputs (``global_map``, ``path``, ``features``, ``pose``),
  and whoever subscribes to them.
- :func:`inbound_qos`: the joiner's inputs (``local_map``, ``pose_graph``), and whoever
  publishes them (the bag player, the tests).
- :func:`bag_topic_qos`: a played bag topic, latched or not.
- :func:`recorder_qos`: the bag recorder's subscriptions.
- :func:`inbound_dds_profile`: the FastDDS profile (``config/fastdds_inbound.xml``) that lets the
  joiner's readers queue a full-speed stream instead of refusing samples.

The bag metadata's form of the first two (rosbags' ``Qos``, written without rclpy) is
:func:`linear_slam_ros.ros.bagio.qos`.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy


def latched_qos() -> QoSProfile:
    """Return the latched profile: reliable, transient local, keep last 1.

    Used by the joiner's ``global_map``, ``path``, ``features`` and ``pose`` publishers, by
    subscribers to them (demo, tests), and by the player for topics a bag marks latched. Each
    message is the whole current state, so only the newest matters; transient local makes the
    publisher hold it for subscribers that join late, which get it only if they ask for
    transient local too (a volatile subscriber receives only later messages).
    """
    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST,
        depth=1,
        reliability=ReliabilityPolicy.RELIABLE,
        durability=DurabilityPolicy.TRANSIENT_LOCAL,
    )


def inbound_qos(depth: int = 0) -> QoSProfile:
    """Return the profile of a submap stream: reliable, volatile, keep all (or keep last ``depth``).

    Used by the joiner's ``local_map`` and ``pose_graph`` subscriptions (``depth`` is its
    ``queue_depth`` parameter) and by whoever publishes those topics (the bag player, the
    tests). Every submap counts, so nothing may be dropped: keep all (``depth`` 0) queues
    messages that arrive faster than they are joined instead of overwriting them. A positive
    ``depth`` keeps only the newest ``depth`` messages, trading completeness for bounded memory.
    """
    return QoSProfile(
        history=HistoryPolicy.KEEP_ALL if depth <= 0 else HistoryPolicy.KEEP_LAST,
        depth=max(depth, 1),
        reliability=ReliabilityPolicy.RELIABLE,
        durability=DurabilityPolicy.VOLATILE,
    )


def bag_topic_qos(latched: bool) -> QoSProfile:
    """Return the profile a player publishes a bag topic with: latched, or a keep-all stream."""
    return latched_qos() if latched else inbound_qos()


def recorder_qos() -> QoSProfile:
    """Return the bag recorder's subscription profile: reliable, transient local, keep all.

    Transient local receives the message a latched publisher (the joiner's ``global_map``)
    already holds when the recorder starts; keep all keeps every later one until it is written,
    however slowly the recorder spins. Only transient-local publishers match it.
    """
    profile = latched_qos()
    profile.history = HistoryPolicy.KEEP_ALL
    return profile


INBOUND_PROFILE = "fastdds_inbound.xml"
"""The joiner's FastDDS profile, in the package's ``config`` folder (installed to its share directory)."""
PROFILE_VARIABLES = ("FASTRTPS_DEFAULT_PROFILES_FILE", "FASTDDS_DEFAULT_PROFILES_FILE")
"""Environment variables through which FastDDS reads an XML profile file (the first is Jazzy's)."""


def inbound_dds_profile(environ: Mapping[str, str], share: Path | None) -> Path | None:
    """Return the FastDDS profile file the joiner should load, or ``None`` to leave DDS as configured.

    Keep-all readers under FastDDS's default resource limits refuse samples beyond 400 queued,
    and the writer's repairs of every refused sample then take a core of CPU (README, "Scale").
    The profile raises the readers' limits (``config/fastdds_inbound.xml``). Nothing is chosen
    when the middleware is not FastDDS or when the user names a profile file of their own.

    Args:
        environ: the process environment.
        share: the package's share directory (``None``: not installed; the source tree's
            ``config`` folder is used).
    """
    if environ.get("RMW_IMPLEMENTATION", "rmw_fastrtps_cpp") not in ("", "rmw_fastrtps_cpp", "rmw_fastrtps_dynamic_cpp"):
        return None
    if any(environ.get(name) for name in PROFILE_VARIABLES):
        return None
    folder = share / "config" if share is not None else Path(__file__).resolve().parents[2] / "config"
    path = folder / INBOUND_PROFILE
    return path if path.is_file() else None
