"""g2o files: reading and writing 2D pose graphs (``VERTEX_SE2`` / ``EDGE_SE2`` lines)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from linear_slam_ros.core.errors import GraphError
from linear_slam_ros.pose_graph.graph import FloatArray, PoseGraph


def read_g2o(path: Path) -> PoseGraph:
    """Read ``VERTEX_SE2`` / ``EDGE_SE2`` lines of a g2o file (other lines are ignored).

    ``EDGE_SE2 i j x y theta I11 I12 I13 I22 I23 I33``: pose ``j`` seen from pose ``i``
    (metres, radians) and the upper triangle of its 3 x 3 information. Vertices named by
    ``VERTEX_SE2`` lines become the graph's poses (their estimates are ignored); without any,
    the poses are those the edges name.

    Args:
        path: the g2o file.

    Returns:
        The 2D graph.

    Raises:
        GraphError: the file cannot be read, a line is malformed (``path:line: ...``), an edge
            names an unknown vertex, or the graph is invalid (see :class:`PoseGraph`).
    """
    vertices: list[int] = []
    f, t, z, info = [], [], [], []
    try:
        lines = Path(path).read_text().splitlines()
    except OSError as exc:
        raise GraphError(f"cannot read {path}: {exc}") from None
    for n, line in enumerate(lines, start=1):
        parts = line.split()
        if not parts:
            continue
        try:
            if parts[0] == "VERTEX_SE2":
                vertices.append(int(parts[1]))
            elif parts[0] == "EDGE_SE2":
                if len(parts) != 12:
                    raise ValueError(f"EDGE_SE2 needs 11 values, got {len(parts) - 1}")
                v = [float(p) for p in parts[3:]]
                u = v[3:]
                f.append(int(parts[1]))
                t.append(int(parts[2]))
                z.append(v[:3])
                info.append([[u[0], u[1], u[2]], [u[1], u[3], u[4]], [u[2], u[4], u[5]]])
        except (ValueError, IndexError) as exc:
            raise GraphError(f"{path}:{n}: {exc}") from None
    return PoseGraph.from_edges(
        f, t, np.array(z).reshape(-1, 3), np.array(info).reshape(-1, 3, 3), vertices or None, dim=2
    )


def write_g2o(path: Path, graph: PoseGraph, poses: dict[int, FloatArray] | None = None) -> None:
    """Write a 2D pose graph (and optional vertex estimates) in g2o's SE2 format.

    Every pose of the graph becomes a ``VERTEX_SE2`` line (its estimate from ``poses``, else
    zeros), every edge an ``EDGE_SE2`` line; values are written with 17 significant digits, so
    :func:`read_g2o` reads back the same float64 values.

    Args:
        path: the file to write (replaced).
        graph: a 2D graph.
        poses: optional ``x y phi`` (m, rad) of some poses, by pose id.

    Raises:
        GraphError: the graph is 3D (g2o's SE2 lines are planar).
    """
    if graph.dim != 2:
        raise GraphError(f"{graph.name}: g2o SE2 lines hold 2D graphs; this graph is {graph.dim}D")
    with open(path, "w") as fh:
        for p in graph.pose_ids.tolist():
            x = poses.get(p, np.zeros(3)) if poses else np.zeros(3)
            fh.write(f"VERTEX_SE2 {p} {x[0]:.17g} {x[1]:.17g} {x[2]:.17g}\n")
        for e in range(graph.n_edges):
            i = graph.information[e]
            z = graph.measurements[e]
            fh.write(
                f"EDGE_SE2 {int(graph.from_ids[e])} {int(graph.to_ids[e])} {z[0]:.17g} {z[1]:.17g} {z[2]:.17g} "
                f"{i[0, 0]:.17g} {i[0, 1]:.17g} {i[0, 2]:.17g} {i[1, 1]:.17g} {i[1, 2]:.17g} {i[2, 2]:.17g}\n"
            )
