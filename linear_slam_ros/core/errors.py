"""Exceptions of linear_slam_ros: one root, one subclass per concern."""

from __future__ import annotations


class LinearSlamError(Exception):
    """Root of every error raised by linear_slam_ros."""


class InvalidMapError(LinearSlamError, ValueError):
    """A local or global map violates its invariants (sizes, finiteness, SPD, ids)."""


class FrameError(LinearSlamError):
    """Two maps share no frame, or a frame pose is missing from a map."""


class DatasetError(LinearSlamError):
    """A dataset file or archive cannot be read or has a malformed entry."""


class SolverError(LinearSlamError):
    """A linear system could not be solved (not positive definite, singular)."""


class GeometryError(LinearSlamError, ValueError):
    """A geometric quantity is degenerate (e.g. coincident frame features)."""


class MessageError(LinearSlamError, ValueError):
    """A ROS message does not follow the documented array layout."""


class GraphError(LinearSlamError, ValueError):
    """A pose graph is malformed: unknown poses, disconnected, bad information."""


class ConfigError(LinearSlamError, ValueError):
    """A configuration value (ROS parameter or command-line option) is not allowed."""
