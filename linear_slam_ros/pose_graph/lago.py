"""LAGO: a closed-form estimate of a 2D pose graph, no initial guess (Carlone et al., RSS 2011).

Given relative-pose edges ``(i, j, z_ij, I_ij)`` — pose ``j`` seen from pose ``i`` in the
datasets' convention — and one anchor pose held at the origin:

1. *Regularisation* (Sec. IV-E). Take a spanning tree (the odometry edges ``(k, k+1)`` when
   they span the graph, otherwise a breadth-first tree), integrate orientations along it, and
   add ``2 k pi`` to each chord's relative orientation, ``k`` rounding the sum around its
   fundamental cycle, so that every cycle sums to about zero.
2. *Phase 1* (eq. 13). Linear estimate of the orientations from ``A^T theta = delta``, with its
   information ``L = A P_delta^-1 A^T``.
3. *Phase 2* (eqs. 9-11). Relative positions rotated into the anchor frame with the estimated
   orientations, ``Delta_g = R(theta_i)^T Delta_l``, keeping their first-order correlation
   with the orientations through ``J = d Delta_g / d theta``.
4. *Phase 3* (eq. 15). One linear solve for positions and orientations, with information
   ``B P_z^-1 B^T``, assembled sparse from the closed form of ``P_z^-1`` in Sec. IV-D.

Each edge's covariance is split block-diagonally (position 2x2, orientation 1x1): the paper's
assumption. When an edge's information couples position and orientation, the cross terms are
dropped — the paper's approximation; :attr:`LagoResult.n_coupled_edges` counts such edges.
"""

from __future__ import annotations

import logging
import time
from collections import deque
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import numpy.typing as npt
import scipy.sparse as sp
import scipy.sparse.csgraph as csgraph

from linear_slam_ros.core.errors import GraphError
from linear_slam_ros.core.geometry import drot2, rot2, wrap_angle
from linear_slam_ros.core.local_map import POSE, LocalMap
from linear_slam_ros.core.solvers import solve_sparse_spd

logger = logging.getLogger(__name__)

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]
TWO_PI = 2.0 * np.pi


@dataclass(frozen=True, eq=False)
class PoseGraph:
    """A 2D pose graph: edges between robot poses.

    Attributes:
        from_ids, to_ids: ``(m,)`` pose ids; edge ``e`` measures ``to`` from ``from``.
        measurements: ``(m, 3)`` ``x y phi`` of pose ``to`` seen from pose ``from``.
        information: ``(m, 3, 3)`` information of each measurement.
        pose_ids: ``(n + 1,)`` every pose of the graph, sorted (vertices without edges included).
    """

    from_ids: IntArray
    to_ids: IntArray
    measurements: FloatArray
    information: FloatArray
    pose_ids: IntArray

    @classmethod
    def from_edges(
        cls,
        from_ids: npt.ArrayLike,
        to_ids: npt.ArrayLike,
        measurements: npt.ArrayLike,
        information: npt.ArrayLike,
        pose_ids: npt.ArrayLike | None = None,
    ) -> "PoseGraph":
        """Build a graph; with ``pose_ids`` given, every edge must name known poses.

        Raises:
            GraphError: an edge names an unknown pose, or shapes do not match.
        """
        f = np.asarray(from_ids, dtype=np.int64)
        t = np.asarray(to_ids, dtype=np.int64)
        z = np.asarray(measurements, dtype=np.float64)
        info = np.asarray(information, dtype=np.float64)
        m = f.size
        if t.shape != (m,) or z.shape != (m, 3) or info.shape != (m, 3, 3):
            raise GraphError(f"pose graph: {m} edges need to ids ({m},), measurements ({m}, 3), information ({m}, 3, 3)")
        if m == 0:
            raise GraphError("pose graph has no edges")
        edge_poses = np.union1d(f, t)
        if pose_ids is None:
            poses = edge_poses
        else:
            poses = np.unique(np.asarray(pose_ids, dtype=np.int64))
            unknown = np.setdiff1d(edge_poses, poses)
            if unknown.size:
                e = int(np.flatnonzero(np.isin(f, unknown) | np.isin(t, unknown))[0])
                raise GraphError(
                    f"edge {e} ({int(f[e])} -> {int(t[e])}) names unknown pose {int(unknown[0])}"
                    f"{f' (and {unknown.size - 1} more)' if unknown.size > 1 else ''}"
                )
        loops = np.flatnonzero(f == t)
        if loops.size:
            raise GraphError(f"edge {int(loops[0])} connects pose {int(f[loops[0]])} to itself")
        if not (np.all(np.isfinite(z)) and np.all(np.isfinite(info))):
            raise GraphError("pose graph has non-finite measurements or information")
        return cls(f, t, z, info, poses)

    @property
    def n_edges(self) -> int:
        """Number of edges."""
        return int(self.from_ids.size)


@dataclass(frozen=True)
class LagoResult:
    """LAGO's estimate.

    Attributes:
        map: poses in the frame of the anchor, with information ``B P_z^-1 B^T``.
        theta_phase1: ``(n,)`` orientations of phase 1, in the order of ``map``'s poses.
        chord_corrections: ``(m,)`` multiples of ``2 pi`` added to each edge's orientation.
        n_coupled_edges: edges whose information coupled position and orientation (dropped).
        seconds: wall time of the estimate.
    """

    map: LocalMap
    theta_phase1: FloatArray
    chord_corrections: IntArray
    n_coupled_edges: int
    seconds: float


def _split_covariances(information: FloatArray) -> tuple[FloatArray, FloatArray, int]:
    """Return per-edge position information (m, 2, 2), orientation information (m,), and how
    many edges had position-orientation cross terms (block-diagonal approximation)."""
    try:
        cov = np.linalg.inv(information)
    except np.linalg.LinAlgError:
        raise GraphError("an edge's information matrix is singular") from None
    coupled = int(np.count_nonzero(np.abs(cov[:, :2, 2]).max(axis=1) > 1e-12 * np.abs(cov).max(axis=(1, 2))))
    var_theta = cov[:, 2, 2]
    if np.any(var_theta <= 0) or np.any(np.linalg.det(cov[:, :2, :2]) <= 0):
        raise GraphError("an edge's information matrix is not positive definite")
    return np.linalg.inv(cov[:, :2, :2]), 1.0 / var_theta, coupled


def spanning_tree(n_nodes: int, tails: IntArray, heads: IntArray, node_ids: IntArray) -> npt.NDArray[np.bool_]:
    """Return a mask of tree edges: the odometry edges (consecutive ids) if they span, else BFS."""
    odometry = np.abs(node_ids[tails] - node_ids[heads]) == 1
    if _spans(n_nodes, tails[odometry], heads[odometry]) and _is_forest(n_nodes, tails[odometry], heads[odometry]):
        return odometry
    adjacency: list[list[tuple[int, int]]] = [[] for _ in range(n_nodes)]
    for e, (a, b) in enumerate(zip(tails.tolist(), heads.tolist())):
        adjacency[a].append((b, e))
        adjacency[b].append((a, e))
    tree = np.zeros(tails.size, dtype=bool)
    seen = np.zeros(n_nodes, dtype=bool)
    seen[0] = True
    queue = deque([0])
    while queue:
        a = queue.popleft()
        for b, e in adjacency[a]:
            if not seen[b]:
                seen[b] = True
                tree[e] = True
                queue.append(b)
    return tree


def _spans(n_nodes: int, tails: IntArray, heads: IntArray) -> bool:
    graph = sp.coo_matrix((np.ones(tails.size), (tails, heads)), shape=(n_nodes, n_nodes))
    return csgraph.connected_components(graph, directed=False)[0] == 1


def _is_forest(n_nodes: int, tails: IntArray, heads: IntArray) -> bool:
    # a spanning set of n - 1 distinct edges is a tree
    pairs = {(min(a, b), max(a, b)) for a, b in zip(tails.tolist(), heads.tolist())}
    return len(pairs) == tails.size == n_nodes - 1


def regularize(
    n_nodes: int, tails: IntArray, heads: IntArray, delta: FloatArray, tree: npt.NDArray[np.bool_], anchor: int
) -> IntArray:
    """Return the multiple ``k`` of ``2 pi`` to add to each edge's orientation (chords only).

    Orientations are integrated along the tree from the anchor; for a chord ``(i, j)`` the
    fundamental cycle's sum is ``theta_i + delta_ij - theta_j``, rounded to a multiple of 2 pi.
    """
    theta = np.full(n_nodes, np.nan)
    theta[anchor] = 0.0
    adjacency: list[list[tuple[int, int, float]]] = [[] for _ in range(n_nodes)]
    for e in np.flatnonzero(tree).tolist():
        a, b = int(tails[e]), int(heads[e])
        adjacency[a].append((b, e, float(delta[e])))
        adjacency[b].append((a, e, -float(delta[e])))
    queue = deque([anchor])
    while queue:
        a = queue.popleft()
        for b, _e, d in adjacency[a]:
            if np.isnan(theta[b]):
                theta[b] = theta[a] + d
                queue.append(b)
    k = np.zeros(tails.size, dtype=np.int64)
    chords = ~tree
    cycle = theta[tails[chords]] + delta[chords] - theta[heads[chords]]
    k[chords] = -np.round(cycle / TWO_PI).astype(np.int64)
    return k


def lago(graph: PoseGraph, anchor_id: int | None = None, regularization: bool = True) -> LagoResult:
    """Estimate every pose of a 2D pose graph in the frame of ``anchor_id`` (default: smallest id).

    ``regularization=False`` skips the 2 k pi chord corrections (for demonstrating why they matter).

    Raises:
        GraphError: the graph is disconnected, or the anchor is not one of its poses.
    """
    t0 = time.perf_counter()
    ids = graph.pose_ids
    anchor_id = int(ids[0]) if anchor_id is None else int(anchor_id)
    index = {int(p): k for k, p in enumerate(ids.tolist())}
    if anchor_id not in index:
        raise GraphError(f"anchor pose {anchor_id} is not in the pose graph")
    tails = np.array([index[int(p)] for p in graph.from_ids.tolist()], dtype=np.int64)
    heads = np.array([index[int(p)] for p in graph.to_ids.tolist()], dtype=np.int64)
    n_all = ids.size
    adjacency = sp.coo_matrix((np.ones(tails.size), (tails, heads)), shape=(n_all, n_all))
    n_comp, labels = csgraph.connected_components(adjacency, directed=False)
    if n_comp > 1:
        lonely = ids[labels != labels[index[anchor_id]]]
        raise GraphError(
            f"pose graph is disconnected: {n_comp} components; pose {int(lonely[0])} is not connected to anchor "
            f"pose {anchor_id} ({lonely.size} poses unreachable)"
        )
    anchor = index[anchor_id]
    m = graph.n_edges
    info_pos, info_theta, coupled = _split_covariances(graph.information)
    if coupled:
        logger.info("LAGO: %d of %d edges couple position and orientation; using the block-diagonal approximation", coupled, m)
    delta = graph.measurements[:, 2].copy()
    tree = spanning_tree(n_all, tails, heads, ids)
    k = regularize(n_all, tails, heads, delta, tree, anchor) if regularization else np.zeros(m, dtype=np.int64)
    delta = delta + TWO_PI * k

    # reduced incidence: unknowns are every pose but the anchor
    keep = np.ones(n_all, dtype=bool)
    keep[anchor] = False
    col = np.full(n_all, -1, dtype=np.int64)
    col[keep] = np.arange(n_all - 1)
    n = n_all - 1
    e_idx = np.arange(m)
    # A^T (m x n): row e has -1 at tail, +1 at head
    rows = np.concatenate([e_idx, e_idx])
    cols = np.concatenate([col[tails], col[heads]])
    vals = np.concatenate([-np.ones(m), np.ones(m)])
    ok = cols >= 0
    at = sp.csr_matrix((vals[ok], (rows[ok], cols[ok])), shape=(m, n))

    # phase 1: orientations
    w_theta = sp.diags(info_theta)
    lap = (at.T @ w_theta @ at).tocsc()
    theta_hat = solve_sparse_spd(lap, at.T @ (info_theta * delta))
    theta_all = np.zeros(n_all)
    theta_all[keep] = theta_hat

    # phase 2: relative positions in the anchor frame, with J = d Delta_g / d theta_tail
    rot_t = np.swapaxes(rot2(theta_all[tails]), -1, -2)  # R(theta_i)^T, local -> anchor frame
    delta_g = np.einsum("eij,ej->ei", rot_t, graph.measurements[:, :2])
    d_rot_t = np.swapaxes(drot2(theta_all[tails]), -1, -2)
    jac_blocks = np.einsum("eij,ej->ei", d_rot_t, graph.measurements[:, :2])  # (m, 2)
    w_pos = rot_t @ info_pos @ np.swapaxes(rot_t, -1, -2)  # P_Delta_g^-1 blocks
    w_g = sp.block_diag(list(w_pos), format="csr")  # (2m, 2m)
    jr = np.repeat(np.arange(2 * m).reshape(m, 2), 1, axis=0)
    jac_rows = jr.ravel()
    jac_cols = np.repeat(col[tails], 2)
    jac_vals = jac_blocks.ravel()
    okj = jac_cols >= 0
    jac = sp.csr_matrix((jac_vals[okj], (jac_rows[okj], jac_cols[okj])), shape=(2 * m, n))
    a2t = sp.kron(at, sp.eye(2), format="csr")  # (2m, 2n): A_2^T

    # phase 3: information B P_z^-1 B^T and right-hand side B P_z^-1 z (Sec. IV-D)
    a2_w = a2t.T @ w_g
    i_rr = a2_w @ a2t
    i_rt = -(a2_w @ jac)
    jt_w = jac.T @ w_g
    i_tt = lap + jt_w @ jac
    info = sp.bmat([[i_rr, i_rt], [i_rt.T, i_tt]], format="csc")
    dg = delta_g.ravel()
    rhs_r = a2_w @ (dg - jac @ theta_hat)
    rhs_t = -(jt_w @ dg) + i_tt @ theta_hat
    p_star = solve_sparse_spd(info, np.concatenate([rhs_r, rhs_t]))
    rho, theta = p_star[: 2 * n].reshape(n, 2), p_star[2 * n :]

    # the map: per pose x y phi, information reordered to match
    x = np.column_stack([rho, wrap_angle(theta)]).ravel()
    perm = np.column_stack([2 * np.arange(n), 2 * np.arange(n) + 1, 2 * n + np.arange(n)]).ravel()
    info_p = info[perm][:, perm].tocsr()
    pose_ids = ids[keep]
    from linear_slam_ros.core.solvers import DENSE_MAX

    stored = info_p.toarray() if info_p.shape[0] <= DENSE_MAX else info_p
    result = LocalMap.trusted(2, anchor_id, None, pose_ids, np.full(n, POSE, dtype=np.int8), x, stored, "lago")
    return LagoResult(result, theta_hat, k, coupled, time.perf_counter() - t0)


def edge_maps(graph: PoseGraph) -> list[LocalMap]:
    """Return each edge as a one-pose local map (for χ² and Gauss-Newton on the graph objective)."""
    maps = []
    for e in range(graph.n_edges):
        maps.append(
            LocalMap.trusted(
                2, int(graph.from_ids[e]), int(graph.to_ids[e]), graph.to_ids[e : e + 1].copy(),
                np.array([POSE], dtype=np.int8), graph.measurements[e].copy(), graph.information[e], f"edge_{e}",
            )
        )
    return maps


def read_g2o(path: Path) -> PoseGraph:
    """Read ``VERTEX_SE2`` / ``EDGE_SE2`` lines of a g2o file (other lines are ignored).

    ``EDGE_SE2 i j x y theta I11 I12 I13 I22 I23 I33`` (upper triangle of the information).

    Raises:
        GraphError: malformed lines or edges to unknown vertices.
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
    return PoseGraph.from_edges(f, t, np.array(z).reshape(-1, 3), np.array(info).reshape(-1, 3, 3), vertices or None)


def write_g2o(path: Path, graph: PoseGraph, poses: dict[int, FloatArray] | None = None) -> None:
    """Write a pose graph (and optional vertex estimates) in g2o's SE2 format."""
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


def graph_from_local_maps(maps: list[LocalMap]) -> PoseGraph:
    """Rebuild a pose graph from pose-only local maps: map ``i`` holds the edges from its frame
    pose to each of its poses (information: the diagonal blocks of the map's)."""
    f, t, z, info = [], [], [], []
    for m in maps:
        if m.dim != 2 or np.any(m.kinds != POSE):
            raise GraphError(f"map {m.name!r} is not a 2D pose-only map")
        dense = m.info_dense()
        for i in range(m.n_vars):
            sl = m.scalar_slice(i)
            f.append(m.frame_id)
            t.append(int(m.ids[i]))
            z.append(m.x[sl])
            info.append(dense[sl, sl])
    return PoseGraph.from_edges(f, t, np.array(z), np.array(info))


def chunk_end_pose(from_ids: IntArray, to_ids: IntArray, frame: int) -> int:
    """Return the last pose of the odometry chain ``frame, frame + 1, ...`` present in the edges."""
    pairs = {(min(a, b), max(a, b)) for a, b in zip(from_ids.tolist(), to_ids.tolist())}
    end = frame
    while (end, end + 1) in pairs:
        end += 1
    return end


def lago_local_map(chunk: object) -> LocalMap:
    """Return the pose-only local map of a 2D pose-graph chunk by LAGO, in its first edge's frame.

    Raises:
        GraphError: the chunk is 3D, or disconnected.
    """
    from linear_slam_ros.pose_graph.chunks import PoseGraphChunk

    assert isinstance(chunk, PoseGraphChunk)
    if chunk.dim != 2:
        raise GraphError(f"pose-graph chunk {chunk.seq}: LAGO is 2D only; this chunk is {chunk.dim}D and not a star")
    graph = PoseGraph.from_edges(chunk.from_ids, chunk.to_ids, chunk.measurements, chunk.information)
    frame = int(chunk.from_ids[0])
    result = lago(graph, anchor_id=frame).map
    end = chunk_end_pose(chunk.from_ids, chunk.to_ids, frame)
    return LocalMap(
        2, frame, end if end != frame else None, result.ids, result.kinds, result.x, result.info,
        name=f"pose_graph chunk {chunk.seq} (LAGO)",
    )
