"""g2o files: reading and writing 2D and 3D pose graphs.

Lines read (g2o's own definitions, ``g2o/types/slam2d`` and ``slam3d``):

- ``VERTEX_SE2 id x y theta`` and ``EDGE_SE2 i j x y theta`` + the upper triangle (row by row)
  of the 3 x 3 information: 6 numbers.
- ``VERTEX_SE3:QUAT id x y z qx qy qz qw`` and ``EDGE_SE3:QUAT i j x y z qx qy qz qw`` + the
  upper triangle of the 6 x 6 information: 21 numbers.

An edge measures pose ``j`` seen from pose ``i``. g2o's error of an edge is
``Z^-1 (X_i^-1 X_j)`` written as its translation and its angle (SE2) or the vector part of
its quaternion (SE3, ``qw >= 0``), so the file's information is over *that* vector: the
translation error is in the frame of the measured pose, and in 3D the rotation error is about
half the rotation angle. :class:`PoseGraph` holds the datasets' convention instead (translation
in the frame of pose ``i``, angles ``alpha beta gamma``): :func:`g2o_to_graph` and
:func:`graph_to_g2o` convert the information exactly to first order at the measurement
(``I = J^T I_g2o J``, ``J`` the Jacobian of g2o's error vector with respect to ours). When an
edge's translation information is isotropic and uncoupled (``s I``, as in the benchmark files)
the rotation leaves it unchanged, and it is copied bit for bit.

:class:`G2oFile` holds a file's numbers as written (g2o's parameters), so
``write_g2o_file(read_g2o_file(f))`` and ``read_g2o_file(write_g2o_file(g))`` are exact; a
2D :class:`PoseGraph` with isotropic translation information also round-trips bit for bit
through :func:`write_g2o` / :func:`read_g2o`, a 3D one to rounding (quaternions, Jacobians).

Other line types (landmarks ``VERTEX_XY`` / ``EDGE_SE2_XY``, ``FIX``, parameters, ...) are not
read: their types and counts are listed in one warning per file, and kept in
:attr:`G2oFile.skipped`. Lines starting with ``#`` are comments.
"""

from __future__ import annotations

import logging
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from linear_slam_ros.core.errors import GraphError
from linear_slam_ros.core.geometry import drot3, rot2, rot3
from linear_slam_ros.core.local_map import ID_BOUND
from linear_slam_ros.pose_graph.graph import FloatArray, IntArray, PoseGraph
from linear_slam_ros.pose_graph.quaternions import angles_to_quaternions, quaternions_to_angles

logger = logging.getLogger(__name__)

VERTEX_TAGS = {2: "VERTEX_SE2", 3: "VERTEX_SE3:QUAT"}
EDGE_TAGS = {2: "EDGE_SE2", 3: "EDGE_SE3:QUAT"}
PARAMETERS = {2: 3, 3: 7}
"""Numbers of a pose in g2o's lines: ``x y theta`` (SE2), ``x y z qx qy qz qw`` (SE3)."""
TANGENT = {2: 3, 3: 6}
"""Size of an edge's error vector and information."""

QUATERNION_MIN_NORM = 1e-6
"""A quaternion of a smaller norm (or a non-finite one) is refused: its normalisation means nothing."""


@dataclass(frozen=True, eq=False)
class G2oFile:
    """The pose-graph lines of a g2o file, as written (g2o's parameters and information).

    Attributes:
        dim: 2 (SE2 lines) or 3 (SE3:QUAT lines).
        vertex_ids: ``(n,)`` ids of the vertex lines, in file order.
        vertex_estimates: ``(n, 3)`` ``x y theta`` or ``(n, 7)`` ``x y z qx qy qz qw``.
        from_ids: ``(m,)`` pose ``i`` of each edge line.
        to_ids: ``(m,)`` pose ``j`` of each edge line.
        measurements: ``(m, 3)`` or ``(m, 7)`` pose ``j`` seen from pose ``i``, g2o's parameters.
        information: ``(m, 3, 3)`` or ``(m, 6, 6)`` symmetric, over g2o's error vector.
        skipped: lines of other types, by type (see the module docstring).
    """

    dim: int
    vertex_ids: IntArray
    vertex_estimates: FloatArray
    from_ids: IntArray
    to_ids: IntArray
    measurements: FloatArray
    information: FloatArray
    skipped: dict[str, int] = field(default_factory=dict)

    def poses(self) -> dict[int, FloatArray]:
        """Return the vertex estimates in the datasets' convention (``x y phi`` / ``x y z alpha beta gamma``)."""
        d = self.dim
        if self.vertex_ids.size == 0:
            return {}
        est = self.vertex_estimates
        angles = est[:, 2:3] if d == 2 else quaternions_to_angles(3, est[:, 3:])
        values = np.concatenate([est[:, :d], angles], 1)
        return {int(k): values[i] for i, k in enumerate(self.vertex_ids.tolist())}


def _upper_to_symmetric(values: list[float], p: int) -> list[list[float]]:
    matrix = [[0.0] * p for _ in range(p)]
    k = 0
    for i in range(p):
        for j in range(i, p):
            matrix[i][j] = matrix[j][i] = values[k]
            k += 1
    return matrix


def _pose_id(text: str) -> int:
    """A pose id of a g2o line (``0 <= id < 2**53``, as every id of the project)."""
    pose_id = int(text)
    if not 0 <= pose_id < ID_BOUND:
        raise ValueError(f"pose id {pose_id} is out of range (0 <= id < 2**53)")
    return pose_id


def _pose_values(dim: int, texts: list[str]) -> list[float]:
    """A pose or measurement of a g2o line (``x y theta`` / ``x y z qx qy qz qw``); a quaternion must have a
    finite norm that is not zero (it is normalised, as g2o does)."""
    values = [float(v) for v in texts]
    if dim == 3:
        norm = float(np.linalg.norm(values[3:7]))
        if not np.isfinite(norm) or norm < QUATERNION_MIN_NORM:
            raise ValueError(f"quaternion (qx qy qz qw) = {tuple(values[3:7])} has norm {norm:g}: not a rotation")
    return values


def read_g2o_file(path: Path) -> G2oFile:
    """Read the pose-graph lines of a g2o file exactly as written.

    Args:
        path: the g2o file.

    Returns:
        Its SE2 or SE3:QUAT vertices and edges; other line types are counted in
        :attr:`G2oFile.skipped` and listed in one warning.

    Raises:
        GraphError: the file cannot be read, a line is malformed (``path:line: ...``), a vertex
            is listed twice, or the file mixes SE2 and SE3 lines.
    """
    try:
        lines = Path(path).read_text(encoding="utf-8-sig").splitlines()  # a byte-order mark is not part of line 1
    except (OSError, UnicodeDecodeError) as exc:
        raise GraphError(f"cannot read {path}: {exc}") from None
    dims: dict[int, int] = {}  # dimension -> first line using it
    vertex_ids: list[int] = []
    vertex_lines: dict[int, int] = {}
    estimates: list[list[float]] = []
    f: list[int] = []
    t: list[int] = []
    z: list[list[float]] = []
    info: list[list[list[float]]] = []
    skipped: Counter[str] = Counter()
    for n, line in enumerate(lines, start=1):
        parts = line.split()
        if not parts or parts[0].startswith("#"):
            continue
        tag = parts[0]
        dim = next((d for d in (2, 3) if tag in (VERTEX_TAGS[d], EDGE_TAGS[d])), None)
        if dim is None:
            skipped[tag] += 1
            continue
        dims.setdefault(dim, n)
        try:
            if tag == VERTEX_TAGS[dim]:
                expected = 1 + PARAMETERS[dim]
                if len(parts) - 1 != expected:
                    raise ValueError(f"{tag} needs {expected} values, got {len(parts) - 1}")
                vid = _pose_id(parts[1])
                if vid in vertex_lines:
                    raise ValueError(f"vertex {vid} is already listed on line {vertex_lines[vid]}")
                vertex_lines[vid] = n
                vertex_ids.append(vid)
                estimates.append(_pose_values(dim, parts[2:]))
            else:
                p = TANGENT[dim]
                expected = 2 + PARAMETERS[dim] + p * (p + 1) // 2
                if len(parts) - 1 != expected:
                    raise ValueError(f"{tag} needs {expected} values, got {len(parts) - 1}")
                values = _pose_values(dim, parts[3:3 + PARAMETERS[dim]]) + [float(v) for v in parts[3 + PARAMETERS[dim]:]]
                f.append(_pose_id(parts[1]))
                t.append(_pose_id(parts[2]))
                z.append(values[: PARAMETERS[dim]])
                info.append(_upper_to_symmetric(values[PARAMETERS[dim] :], p))
        except ValueError as exc:
            raise GraphError(f"{path}:{n}: {exc}") from None
    if len(dims) > 1:
        raise GraphError(f"{path}: mixes SE2 (from line {dims[2]}) and SE3 (from line {dims[3]}) lines; one graph is 2D or 3D")
    if skipped:
        listed = ", ".join(f"{tag} ({count})" for tag, count in sorted(skipped.items()))
        logger.warning("%s: lines not read (only SE2 and SE3:QUAT poses and edges are): %s", path, listed)
    dim = next(iter(dims), 2)
    k, p = PARAMETERS[dim], TANGENT[dim]
    return G2oFile(
        dim,
        np.array(vertex_ids, dtype=np.int64),
        np.array(estimates, dtype=np.float64).reshape(-1, k),
        np.array(f, dtype=np.int64),
        np.array(t, dtype=np.int64),
        np.array(z, dtype=np.float64).reshape(-1, k),
        np.array(info, dtype=np.float64).reshape(-1, p, p),
        dict(skipped),
    )


def write_g2o_file(path: Path, g2o: G2oFile) -> None:
    """Write vertices then edges in g2o's lines, with 17 significant digits (read back exactly).

    Args:
        path: the file to write (replaced).
        g2o: what to write; :attr:`G2oFile.skipped` is not written.
    """
    vertex, edge = VERTEX_TAGS[g2o.dim], EDGE_TAGS[g2o.dim]
    upper = np.triu_indices(TANGENT[g2o.dim])
    with open(path, "w") as fh:
        for vid, est in zip(g2o.vertex_ids.tolist(), g2o.vertex_estimates, strict=True):
            fh.write(f"{vertex} {vid} " + " ".join(f"{v:.17g}" for v in est) + "\n")
        for e in range(g2o.from_ids.size):
            numbers = np.concatenate([g2o.measurements[e], g2o.information[e][upper]])
            fh.write(f"{edge} {int(g2o.from_ids[e])} {int(g2o.to_ids[e])} " + " ".join(f"{v:.17g}" for v in numbers) + "\n")


def _error_jacobians(dim: int, angles: FloatArray) -> FloatArray:
    """Return ``J`` ``(m, p, p)``: d(g2o's error vector) / d(our measurement vector) at the measurement.

    The translation error is ``R (t - t_z)`` (``R`` the passive rotation of the measured angles);
    in 3D the rotation error is the vector part of the quaternion of ``R_z R(angles)^T``,
    whose derivative along angle ``k`` is ``vee(R_z dR_k^T) / 2``.
    """
    m = angles.shape[0]
    p = TANGENT[dim]
    jac = np.zeros((m, p, p))
    if dim == 2:
        jac[:, :2, :2] = rot2(angles[:, 0])
        jac[:, 2, 2] = 1.0
        return jac
    rot = rot3(angles)
    skew = rot[:, None, :, :] @ np.swapaxes(drot3(angles), -1, -2)  # (m, k, 3, 3)
    jac[:, :3, :3] = rot
    jac[:, 3:, 3:] = 0.5 * np.stack([skew[..., 2, 1], skew[..., 0, 2], skew[..., 1, 0]], -1).swapaxes(-1, -2)
    return jac


def _transform_information(information: FloatArray, jac: FloatArray, dim: int) -> FloatArray:
    """Return ``J^T I J`` per edge, symmetrised; isotropic uncoupled translation blocks are kept as they are."""
    out = np.einsum("mki,mkl,mlj->mij", jac, information, jac)
    out = 0.5 * (out + np.swapaxes(out, 1, 2))
    d = dim
    tt = information[:, :d, :d]
    iso = np.all(tt == tt[:, :1, :1] * np.eye(d), axis=(1, 2)) & np.all(information[:, :d, d:] == 0.0, axis=(1, 2))
    out[iso, :d, :d] = tt[iso]
    out[iso, :d, d:] = 0.0
    out[iso, d:, :d] = 0.0
    return out


def g2o_to_graph(g2o: G2oFile, name: str = "g2o graph") -> PoseGraph:
    """Return the pose graph of a g2o file's lines, in the datasets' convention.

    Measurements become ``x y phi`` / ``x y z alpha beta gamma``, the information is converted
    to first order at the measurement (module docstring). The vertices are the graph's poses;
    without any, the poses the edges name.

    Raises:
        GraphError: an edge names an unknown vertex, or the graph is invalid (:class:`PoseGraph`).
    """
    d = g2o.dim
    z = g2o.measurements
    angles = z[:, 2:3] if d == 2 else quaternions_to_angles(3, z[:, 3:])
    measurements = np.concatenate([z[:, :d], angles], 1)
    information = _transform_information(g2o.information, _error_jacobians(d, angles), d)
    return PoseGraph.from_edges(
        g2o.from_ids, g2o.to_ids, measurements, information, g2o.vertex_ids if g2o.vertex_ids.size else None, dim=d, name=name
    )


def graph_to_g2o(graph: PoseGraph, poses: dict[int, FloatArray] | None = None) -> G2oFile:
    """Return the g2o lines of a pose graph (inverse of :func:`g2o_to_graph`).

    Args:
        graph: a 2D or 3D graph.
        poses: optional estimates of some poses, by id, in the datasets' convention; the other
            vertices are written at the origin.

    Raises:
        GraphError: an estimate is not a pose of the graph's dimension.
    """
    d = graph.dim
    z = graph.measurements
    angles = z[:, d:]
    parameters = z[:, 2:3] if d == 2 else angles_to_quaternions(3, angles)
    inverse = np.asarray(np.linalg.inv(_error_jacobians(d, angles)), dtype=np.float64)
    information = _transform_information(graph.information, inverse, d)
    values = np.zeros((graph.n_poses, d + angles.shape[1]))
    for i, pid in enumerate(graph.pose_ids.tolist()):
        if poses is not None and pid in poses:
            value = np.asarray(poses[pid], dtype=np.float64)
            if value.shape != values.shape[1:]:
                raise GraphError(f"{graph.name}: the estimate of pose {pid} has shape {value.shape}, expected {values.shape[1:]}")
            values[i] = value
    vertex_angles = values[:, d:] if d == 2 else angles_to_quaternions(3, values[:, d:])
    return G2oFile(
        d, graph.pose_ids.copy(), np.concatenate([values[:, :d], vertex_angles], 1), graph.from_ids.copy(),
        graph.to_ids.copy(), np.concatenate([z[:, :d], parameters], 1), information,
    )


def read_g2o(path: Path) -> PoseGraph:
    """Read a 2D (``VERTEX_SE2`` / ``EDGE_SE2``) or 3D (``VERTEX_SE3:QUAT`` / ``EDGE_SE3:QUAT``) g2o file.

    ``EDGE_SE2 i j x y theta I11 I12 I13 I22 I23 I33``: pose ``j`` seen from pose ``i``
    (metres, radians) and the upper triangle of its information; SE3 edges likewise with a
    quaternion and 21 numbers. Vertices become the graph's poses (their estimates:
    :meth:`G2oFile.poses`); without any, the poses are those the edges name. Other line types
    are listed in one warning.

    Args:
        path: the g2o file.

    Returns:
        The graph, named after the file, in the datasets' convention (module docstring).

    Raises:
        GraphError: the file cannot be read, a line is malformed (``path:line: ...``), an edge
            names an unknown vertex, or the graph is invalid (see :class:`PoseGraph`).
    """
    return g2o_to_graph(read_g2o_file(path), name=str(path))


def write_g2o(path: Path, graph: PoseGraph, poses: dict[int, FloatArray] | None = None) -> None:
    """Write a pose graph (and optional vertex estimates) as g2o SE2 (2D) or SE3:QUAT (3D) lines.

    Every pose of the graph becomes a vertex line (its estimate from ``poses``, else the
    origin), every edge an edge line; numbers have 17 significant digits, so :func:`read_g2o`
    reads back the same graph (bit for bit in 2D with isotropic translation information).

    Args:
        path: the file to write (replaced).
        graph: a 2D or 3D graph.
        poses: optional ``x y phi`` / ``x y z alpha beta gamma`` (m, rad) of some poses, by id.
    """
    write_g2o_file(path, graph_to_g2o(graph, poses))


__all__ = [
    "G2oFile",
    "g2o_to_graph",
    "graph_to_g2o",
    "read_g2o",
    "read_g2o_file",
    "write_g2o",
    "write_g2o_file",
]

