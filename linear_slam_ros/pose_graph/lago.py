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

This module holds the estimator (:func:`lago`, its result :class:`LagoResult`, and the spanning
tree and regularisation it uses); turning a graph into a local map by LAGO is
:func:`linear_slam_ros.pose_graph.chunks.lago_local_map`.
"""

from __future__ import annotations

import logging
import time
from collections import deque
from dataclasses import dataclass
from typing import cast

import numpy as np
import numpy.typing as npt
import scipy.sparse as sp
import scipy.sparse.csgraph as csgraph

from linear_slam_ros.core.errors import GraphError
from linear_slam_ros.core.geometry import drot2, rot2, wrap_angle
from linear_slam_ros.core.local_map import POSE, LocalMap
from linear_slam_ros.core.solvers import DENSE_MAX, solve_sparse_spd
from linear_slam_ros.pose_graph.graph import FloatArray, IntArray, PoseGraph

logger = logging.getLogger(__name__)

TWO_PI = 2.0 * np.pi


@dataclass(frozen=True)
class LagoResult:
    """LAGO's estimate.

    Attributes:
        map: every pose but the anchor, ``x y phi`` (m, rad) in the frame of the anchor pose,
            with information ``B P_z^-1 B^T`` (``end_id`` None, name ``"lago"``).
        theta_phase1: ``(n,)`` orientations of phase 1 (rad, not wrapped), in the order of
            ``map``'s poses.
        chord_corrections: ``(m,)`` multiples of ``2 pi`` added to each edge's orientation.
        n_coupled_edges: edges whose information coupled position and orientation (dropped).
        seconds: wall time of the estimate (s).
    """

    map: LocalMap
    theta_phase1: FloatArray
    chord_corrections: IntArray
    n_coupled_edges: int
    seconds: float


def _split_covariances(information: FloatArray) -> tuple[FloatArray, FloatArray, int]:
    """Split each edge's covariance block-diagonally (the paper's assumption).

    Args:
        information: ``(m, 3, 3)`` information of each edge (``x y phi``).

    Returns:
        Per-edge position information ``(m, 2, 2)`` (1/m²), orientation information ``(m,)``
        (1/rad²), and how many edges had position-orientation cross terms (dropped).

    Raises:
        GraphError: an edge's information is singular or not positive definite.
    """
    try:
        cov = np.linalg.inv(information)
    except np.linalg.LinAlgError:
        raise GraphError("an edge's information matrix is singular") from None
    coupled = int(np.count_nonzero(np.abs(cov[:, :2, 2]).max(axis=1) > 1e-12 * np.abs(cov).max(axis=(1, 2))))
    var_theta = cov[:, 2, 2]
    if np.any(var_theta <= 0) or np.any(np.linalg.det(cov[:, :2, :2]) <= 0):
        raise GraphError("an edge's information matrix is not positive definite")
    return np.linalg.inv(cov[:, :2, :2]), cast(FloatArray, 1.0 / var_theta), coupled


def spanning_tree(n_nodes: int, tails: IntArray, heads: IntArray, node_ids: IntArray) -> npt.NDArray[np.bool_]:
    """Return a spanning tree of the graph as a mask of its edges.

    The odometry edges (between consecutive pose ids) when they form a spanning tree, else a
    breadth-first tree from node 0.

    Args:
        n_nodes: number of nodes.
        tails, heads: ``(m,)`` node indices (``0 .. n_nodes - 1``) of each edge's ends.
        node_ids: ``(n_nodes,)`` pose id of each node.

    Returns:
        ``(m,)`` True for the tree's edges.
    """
    odometry = np.abs(node_ids[tails] - node_ids[heads]) == 1
    if _spans(n_nodes, tails[odometry], heads[odometry]) and _is_forest(n_nodes, tails[odometry], heads[odometry]):
        return odometry
    adjacency: list[list[tuple[int, int]]] = [[] for _ in range(n_nodes)]
    for e, (a, b) in enumerate(zip(tails.tolist(), heads.tolist(), strict=True)):
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
    """Whether the edges ``tails[e] - heads[e]`` connect all ``n_nodes`` nodes."""
    graph = sp.coo_matrix((np.ones(tails.size), (tails, heads)), shape=(n_nodes, n_nodes))
    return csgraph.connected_components(graph, directed=False)[0] == 1


def _is_forest(n_nodes: int, tails: IntArray, heads: IntArray) -> bool:
    """Whether the edges are ``n_nodes - 1`` distinct pairs (a spanning set of them is a tree)."""
    pairs = {(min(a, b), max(a, b)) for a, b in zip(tails.tolist(), heads.tolist(), strict=True)}
    return len(pairs) == tails.size == n_nodes - 1


def regularize(
    n_nodes: int, tails: IntArray, heads: IntArray, delta: FloatArray, tree: npt.NDArray[np.bool_], anchor: int
) -> IntArray:
    """Return the multiple ``k`` of ``2 pi`` to add to each edge's orientation (chords only).

    Orientations are integrated along the tree from the anchor; for a chord ``(i, j)`` the
    fundamental cycle's sum is ``theta_i + delta_ij - theta_j``, rounded to a multiple of 2 pi.

    Args:
        n_nodes: number of nodes.
        tails, heads: ``(m,)`` node indices of each edge's ends.
        delta: ``(m,)`` each edge's relative orientation (rad).
        tree: ``(m,)`` mask of the spanning tree's edges (see :func:`spanning_tree`).
        anchor: node index held at orientation 0.

    Returns:
        ``(m,)`` integer ``k`` per edge, 0 on tree edges.
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
    """Estimate every pose of a 2D pose graph in the frame of one of its poses.

    Args:
        graph: a connected 2D graph.
        anchor_id: the pose held at the origin (default: the smallest pose id).
        regularization: ``False`` skips the 2 k pi chord corrections (for demonstrating why
            they matter).

    Returns:
        The estimate of every other pose in the anchor's frame, with its information.

    Raises:
        GraphError: the graph is 3D or disconnected, or the anchor is not one of its poses.
    """
    t0 = time.perf_counter()
    if graph.dim != 2:
        raise GraphError(f"{graph.name}: LAGO is 2D only; this graph is {graph.dim}D")
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
    info = cast(sp.csc_matrix, sp.bmat([[i_rr, i_rt], [i_rt.T, i_tt]], format="csc"))
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
    stored = info_p.toarray() if info_p.shape[0] <= DENSE_MAX else info_p
    result = LocalMap.trusted(2, anchor_id, None, pose_ids, np.full(n, POSE, dtype=np.int8), x, stored, "lago")
    return LagoResult(result, theta_hat, k, coupled, time.perf_counter() - t0)
