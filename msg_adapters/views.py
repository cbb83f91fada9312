"""Core maps -> the standard messages a person looks at (nav_msgs/Path, MarkerArray,
PoseWithCovarianceStamped, TransformStamped).

Orientation convention: a dataset pose's ``R`` maps world directions into the robot frame, so
the robot's orientation in the world (what ROS poses carry) is ``R^T``. In 3D,
``R = RX(gamma) RY(beta) RZ(alpha)`` (passive) gives ``R^T = Rz(alpha) Ry(beta) Rx(gamma)``
(active): the ROS roll, pitch and yaw of the pose are ``gamma``, ``beta`` and ``alpha``; in 2D
the yaw is ``phi``. Covariances are reordered accordingly (:func:`ros_pose_covariance`).
"""

from __future__ import annotations

import functools
from collections.abc import Mapping
from typing import NamedTuple

import numpy as np
import numpy.typing as npt
import scipy.linalg.lapack
from builtin_interfaces.msg import Time
from geometry_msgs.msg import (
    Point,
    Pose,
    PoseStamped,
    PoseWithCovarianceStamped,
    Quaternion,
    Transform,
    TransformStamped,
    Vector3,
)
from nav_msgs.msg import Path
from scipy.spatial.transform import Rotation
from std_msgs.msg import ColorRGBA, Header
from visualization_msgs.msg import Marker, MarkerArray

from linear_slam_ros.core.frames import change_frame, estimate_in_frame
from linear_slam_ros.core.geometry import pose_size, rotation
from linear_slam_ros.core.local_map import FEATURE, POSE, LocalMap, to_dense
from linear_slam_ros.feature_only.maps import FeatureMap, expansion_matrix

FloatArray = npt.NDArray[np.float64]

ELLIPSE_SIGMA = 2.0
"""Covariance ellipses are drawn at this many standard deviations."""

MIN_MARKER_SCALE = 1e-3
"""Smallest axis of a covariance ellipse, m: a variance of zero (a feature-only map's frame
features, fixed in their own frame) is drawn this thin, since RViz refuses a marker of scale 0."""


def stamp_msg(nanoseconds: int) -> Time:
    """Return a time in nanoseconds as a ``builtin_interfaces/Time``."""
    sec, nanosec = divmod(nanoseconds, 1_000_000_000)
    return Time(sec=sec, nanosec=nanosec)


def pose_to_msg(dim: int, pose: FloatArray) -> Pose:
    """Return a ``geometry_msgs/Pose`` of a dataset-convention pose."""
    return pose_msgs(dim, np.asarray(pose, dtype=np.float64)[None, :])[0]


def pose_msgs(dim: int, poses: FloatArray) -> list[Pose]:
    """Return ``geometry_msgs/Pose`` messages of dataset-convention poses ``(n, 3)`` or ``(n, 6)`` (one rotation call)."""
    if dim == 2:  # R(phi)^T turns by +phi about z
        half = poses[:, 2] / 2.0
        quats = np.stack([np.zeros_like(half), np.zeros_like(half), np.sin(half), np.cos(half)], -1)
        quats[quats[:, 3] < 0] *= -1.0  # w >= 0, as scipy's canonical form
        quat_rows = quats.tolist()
    else:
        body_to_world = np.swapaxes(rotation(dim, poses[:, dim:]), -1, -2)
        quat_rows = Rotation.from_matrix(body_to_world).as_quat(canonical=True).reshape(-1, 4).tolist() if poses.shape[0] else []
    xyz = np.zeros((poses.shape[0], 3))
    xyz[:, :dim] = poses[:, :dim]
    return [
        Pose(position=Point(x=x, y=y, z=z), orientation=Quaternion(x=qx, y=qy, z=qz, w=qw))
        for (x, y, z), (qx, qy, qz, qw) in zip(xyz.tolist(), quat_rows, strict=True)
    ]


def path_msg(global_map: LocalMap, frame_id: str, stamp: Time, pose_stamps: Mapping[int, int] | None = None) -> Path:
    """Return the robot poses of a map (in the frame of its first pose) as a ``nav_msgs/Path``, by pose id.

    Args:
        global_map: the map.
        frame_id: ``header.frame_id`` of the path and of each pose.
        stamp: the path's stamp, and that of each pose without one of its own.
        pose_stamps: ``{pose id: stamp (ns)}`` of the poses whose time is known (the node: each
            joined submap's end pose); a pose not in it carries ``stamp``.
    """
    header = Header(stamp=stamp, frame_id=frame_id)
    dim = global_map.dim
    pose_vars = np.flatnonzero(global_map.kinds == POSE)
    ids = np.concatenate([[global_map.frame_id], global_map.ids[pose_vars]])
    poses = np.zeros((ids.size, pose_size(dim)))
    if pose_vars.size:
        poses[1:] = global_map.x[global_map.scalar_index(pose_vars)].reshape(-1, pose_size(dim))
    order = np.argsort(ids, kind="stable")
    own = pose_stamps or {}
    headers = [Header(stamp=stamp_msg(own[i]), frame_id=frame_id) if i in own else header for i in ids[order].tolist()]
    msg = Path(header=header)
    msg.poses = [PoseStamped(header=h, pose=p) for h, p in zip(headers, pose_msgs(dim, poses[order]), strict=True)]
    return msg


def pose_stamped_msg(dim: int, pose: FloatArray, frame_id: str, stamp: Time) -> PoseStamped:
    """Return a dataset-convention pose (``(3,)`` or ``(6,)``, in frame ``frame_id``) as ``geometry_msgs/PoseStamped``."""
    return PoseStamped(header=Header(stamp=stamp, frame_id=frame_id), pose=pose_to_msg(dim, pose))


ROS_POSE_ORDER = {2: (0, 1, 5), 3: (0, 1, 2, 5, 4, 3)}
"""Row of the ROS 6x6 pose covariance (``x y z roll pitch yaw``) of each dataset-convention
coordinate: 2D ``x y phi``, 3D ``x y z alpha beta gamma`` (``alpha`` is the yaw, ``gamma`` the roll)."""

_ROS_FLAT_INDEX = {d: (6 * np.asarray(r)[:, None] + np.asarray(r)[None, :]).reshape(-1) for d, r in ROS_POSE_ORDER.items()}
"""Where each entry of a row-major dataset-convention covariance goes in the flat ROS 6x6 matrix."""


def ros_pose_covariance(dim: int, cov: FloatArray) -> FloatArray:
    """Return a dataset-convention pose covariance as the 36 row-major values of a ROS pose covariance.

    Args:
        dim: 2 or 3.
        cov: ``(3, 3)`` covariance of ``x y phi`` or ``(6, 6)`` of ``x y z alpha beta gamma``
            (m², m·rad, rad²).

    Returns:
        ``(36,)``: the 6x6 matrix over ``x y z roll pitch yaw`` (m², m·rad, rad²), row-major.
        2D: the ``x y yaw`` rows and columns carry ``cov``; the ``z``, ``roll`` and ``pitch``
        rows and columns are zero (a planar robot: those coordinates are fixed; slam_toolbox's
        pose fills the same entries).
    """
    out = np.zeros(36)
    out[_ROS_FLAT_INDEX[dim]] = np.asarray(cov, dtype=np.float64).reshape(-1)
    return out


def pose_with_covariance_msg(
    dim: int, pose: FloatArray, cov: FloatArray | None, frame_id: str, stamp: Time
) -> PoseWithCovarianceStamped:
    """Return a dataset-convention pose and its covariance as ``geometry_msgs/PoseWithCovarianceStamped``.

    Args:
        dim: 2 or 3.
        pose: ``(3,)`` or ``(6,)`` in frame ``frame_id`` (m, rad).
        cov: its covariance (see :func:`ros_pose_covariance`); ``None``: unknown, written as
            ``-1`` in the first element and zeros elsewhere (the ``sensor_msgs`` convention).
        frame_id: ``header.frame_id``.
        stamp: header stamp.
    """
    msg = PoseWithCovarianceStamped(header=Header(stamp=stamp, frame_id=frame_id))
    msg.pose.pose = pose_to_msg(dim, pose)
    msg.pose.covariance = ros_pose_covariance(dim, cov) if cov is not None else np.array([-1.0] + [0.0] * 35)
    return msg


def transform_msg(dim: int, pose: FloatArray, parent_frame: str, child_frame: str, stamp: Time) -> TransformStamped:
    """Return a dataset-convention pose as the ``geometry_msgs/TransformStamped`` ``parent_frame`` -> ``child_frame``.

    ``pose`` is the child frame's pose in the parent frame (``(3,)`` or ``(6,)``, m and rad):
    the transform maps child coordinates into the parent frame, as TF's do.
    """
    p = pose_to_msg(dim, pose)
    translation = Vector3(x=p.position.x, y=p.position.y, z=p.position.z)
    header = Header(stamp=stamp, frame_id=parent_frame)
    return TransformStamped(
        header=header, child_frame_id=child_frame, transform=Transform(translation=translation, rotation=p.orientation)
    )


def feature_markers(
    global_map: LocalMap, frame_id: str, stamp: Time, covariances: dict[int, FloatArray] | None = None
) -> MarkerArray:
    """Return the features of a map (in the frame of its first pose) as markers: see :func:`point_markers`."""
    feats = np.flatnonzero(global_map.kinds == FEATURE).tolist()
    points = {int(global_map.ids[i]): global_map.x[global_map.scalar_slice(i)] for i in feats}
    return point_markers(global_map.dim, points, frame_id, stamp, covariances)


def point_markers(
    dim: int, points: dict[int, FloatArray], frame_id: str, stamp: Time, covariances: dict[int, FloatArray] | None = None
) -> MarkerArray:
    """Return the features as a point list plus, where given, one 2-sigma ellipse (ellipsoid) each.

    The message starts with a ``DELETEALL``, so marker ids only tell this message's markers apart:
    the ellipses are numbered from 0 in namespace ``covariance``, each with its feature's id in
    ``text``. (A feature id need not fit ``Marker.id``, an int32: robot k's features are
    k·2³² + i, and ids that wrapped would overwrite one another's ellipse.)

    Args:
        dim: 2 or 3.
        points: ``{feature id: (d,) position}`` in the frame ``frame_id``.
        frame_id: ``map_frame``.
        stamp: header stamp.
        covariances: ``{feature id: (d, d) marginal covariance}``.
    """
    header = Header(stamp=stamp, frame_id=frame_id)
    d = dim
    markers_points = Marker(header=header, ns="features", id=0, type=Marker.SPHERE_LIST, action=Marker.ADD)
    markers_points.pose.orientation.w = 1.0
    markers_points.scale.x = markers_points.scale.y = markers_points.scale.z = 0.3
    markers_points.color = ColorRGBA(r=0.1, g=0.3, b=0.9, a=1.0)
    for x in points.values():
        markers_points.points.append(Point(x=float(x[0]), y=float(x[1]), z=float(x[2]) if d == 3 else 0.0))
    # an empty namespace: RViz 2 deletes only the markers of a DELETEALL's namespace when it has one
    markers = [Marker(header=header, ns="", action=Marker.DELETEALL), markers_points]
    for fid, x in points.items() if covariances else []:
        cov = covariances.get(fid) if covariances else None
        if cov is None:
            continue
        values, vectors = np.linalg.eigh(0.5 * (cov + cov.T))
        values = np.clip(values, 0.0, None)
        if np.linalg.det(vectors) < 0:
            vectors[:, 0] = -vectors[:, 0]
        m = Marker(header=header, ns="covariance", id=len(markers) - 2, action=Marker.ADD, text=str(fid))
        m.pose.position = Point(x=float(x[0]), y=float(x[1]), z=float(x[2]) if d == 3 else 0.0)
        axes = np.maximum(2.0 * ELLIPSE_SIGMA * np.sqrt(values), MIN_MARKER_SCALE)  # full axis lengths
        if d == 2:
            m.type = Marker.CYLINDER
            full = np.eye(3)
            full[:2, :2] = vectors
            vectors = full
            m.scale.x, m.scale.y, m.scale.z = float(axes[0]), float(axes[1]), 0.02
        else:
            m.type = Marker.SPHERE
            m.scale.x, m.scale.y, m.scale.z = (float(a) for a in axes)
        qx, qy, qz, qw = Rotation.from_matrix(vectors).as_quat()
        m.pose.orientation = Quaternion(x=float(qx), y=float(qy), z=float(qz), w=float(qw))
        m.color = ColorRGBA(r=0.9, g=0.4, b=0.1, a=0.35)
        markers.append(m)
    return MarkerArray(markers=markers)


def spd_inverse(matrix: FloatArray) -> FloatArray:
    """Return the inverse of a symmetric positive-definite matrix by Cholesky (LAPACK potrf/potri: a third of ``inv``'s work)."""
    factor, info = scipy.linalg.lapack.dpotrf(matrix, lower=0)
    if info != 0:  # not positive definite (cannot happen for a joined map): the general inverse
        return np.asarray(np.linalg.inv(matrix), dtype=np.float64)
    inv_upper, info = scipy.linalg.lapack.dpotri(factor, lower=0)
    upper = np.triu(inv_upper)
    return np.asarray(upper + np.triu(upper, 1).T, dtype=np.float64)


def feature_covariances(global_map: LocalMap, max_state: int) -> dict[int, FloatArray] | None:
    """Return each feature's marginal covariance, or ``None`` above ``max_state`` scalars."""
    if global_map.state_dim > max_state or not np.any(global_map.kinds == FEATURE):
        return None
    cov = spd_inverse(global_map.info_dense())
    out: dict[int, FloatArray] = {}
    for i in np.flatnonzero(global_map.kinds == FEATURE).tolist():
        sl = global_map.scalar_slice(i)
        out[int(global_map.ids[i])] = cov[sl, sl]
    return out


def feature_map_covariances(feature_map: FeatureMap, max_state: int) -> dict[int, FloatArray] | None:
    """Return each feature's marginal covariance in a feature-only map's frame, or ``None`` above
    ``max_state`` scalars (the frame features' fixed coordinates have zero variance)."""
    if feature_map.state_dim > max_state:
        return None
    d = feature_map.dim
    expand = expansion_matrix(d, feature_map.all_ids.size).toarray()
    cov = expand @ np.linalg.inv(to_dense(feature_map.info)) @ expand.T
    return {int(f): cov[k * d : (k + 1) * d, k * d : (k + 1) * d] for k, f in enumerate(feature_map.all_ids.tolist())}


class MapViews(NamedTuple):
    """The viewing messages of a joined map (``None``: the map type has no such view).

    The newest pose (with its covariance) is not a view: the node computes its covariance
    (:mod:`linear_slam_ros.core.pose_covariance`) and converts it with :func:`pose_with_covariance_msg`.
    """

    path: Path | None
    markers: MarkerArray


@functools.singledispatch
def map_views(
    joined: object, first_pose_id: int | None, frame_id: str, stamp: Time, ellipse_max_state: int,
    pose_stamps: Mapping[int, int] | None = None,
) -> MapViews:
    """Return the viewing messages of a joined map, in ``frame_id``.

    Args:
        joined: the map (a type registered below; a feature-only map is drawn in its own frame).
        first_pose_id: the pose whose frame ``frame_id`` names (pose maps are moved there).
        frame_id: ``header.frame_id`` of the messages.
        stamp: their stamp.
        ellipse_max_state: no covariance ellipses above this many state scalars.
        pose_stamps: ``{pose id: stamp (ns)}``: the path's poses whose time is known (:func:`path_msg`).

    Raises:
        TypeError: no views are registered for the map's type.
    """
    raise TypeError(f"no views for {type(joined).__name__}")


@map_views.register
def _(
    joined: LocalMap, first_pose_id: int | None, frame_id: str, stamp: Time, ellipse_max_state: int,
    pose_stamps: Mapping[int, int] | None = None,
) -> MapViews:
    first = joined.frame_id if first_pose_id is None else first_pose_id
    if joined.state_dim <= ellipse_max_state:  # the ellipses need the information in the first frame too
        in_first = joined if joined.frame_id == first else change_frame(joined, first)
    else:
        in_first = estimate_in_frame(joined, first)
    markers = feature_markers(in_first, frame_id, stamp, feature_covariances(in_first, ellipse_max_state))
    return MapViews(path_msg(in_first, frame_id, stamp, pose_stamps), markers)


@map_views.register
def _(
    joined: FeatureMap, first_pose_id: int | None, frame_id: str, stamp: Time, ellipse_max_state: int,
    pose_stamps: Mapping[int, int] | None = None,
) -> MapViews:
    covs = feature_map_covariances(joined, ellipse_max_state)
    return MapViews(None, point_markers(joined.dim, joined.positions(), frame_id, stamp, covs))


def empty_views(frame_id: str, stamp: Time) -> MapViews:
    """Return the views of an empty map: an empty path and a marker array that deletes every marker."""
    header = Header(frame_id=frame_id, stamp=stamp)
    return MapViews(Path(header=header), MarkerArray(markers=[Marker(header=header, action=Marker.DELETEALL)]))
