"""Conversions between pose graphs and pose-only local maps.

A *star* graph (every edge leaves one pose, as in the benchmark pose-only datasets and the
``pose_graph`` chunks made from them) is already a pose-only local map in the frame of that
pose: its estimate is the measurements, its information block diagonal, with repeated edges
fused. Other graphs need a closed-form estimate of their own (LAGO, 2D) before they can be
joined. The other way round, local maps give back the edges they hold
(:func:`graph_from_local_maps`), and each edge is a one-pose local map (:func:`edge_maps`) for
the χ² of the graph objective.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence

import numpy as np
import numpy.typing as npt
import scipy.sparse as sp

from linear_slam_ros.core.errors import GraphError, InvalidMapError
from linear_slam_ros.core.geometry import pose_size, poses_to_frame, wrap_angle
from linear_slam_ros.core.limits import InputLimits
from linear_slam_ros.core.local_map import POSE, InfoMatrix, LocalMap, check_block_diagonal_condition, default_end_pose
from linear_slam_ros.core.solvers import DENSE_MAX
from linear_slam_ros.pose_graph.graph import FloatArray, IntArray, PoseGraph
from linear_slam_ros.pose_graph.lago import lago

logger = logging.getLogger(__name__)


def star_chunk_to_local_map(graph: PoseGraph, limits: InputLimits | None = None) -> LocalMap:
    """Return the pose-only local map of a star graph, in the frame of its centre pose.

    Args:
        graph: a graph whose edges all leave one pose.
        limits: the numeric bounds the map is validated with (default limits when None).

    Returns:
        Every pose the edges reach, ``measurements`` as the estimate (m, rad) and the edges'
        information on the block diagonal (dense up to ``DENSE_MAX`` scalars, else CSR: never
        densified); repeated edges to one pose are fused (:func:`fuse_star_edges`). The map's
        end pose is :func:`linear_slam_ros.core.local_map.default_end_pose`; its name is the
        graph's.

    Raises:
        GraphError: the graph is not a star, or its map is invalid.
    """
    if not graph.is_star:
        raise GraphError(
            f"{graph.name} is not a star (edges leave poses {sorted(set(graph.from_ids.tolist()))[:5]}): "
            "it needs a closed-form estimate (LAGO) first"
        )
    frame = int(graph.from_ids[0])
    ids, values, blocks = fuse_star_edges(graph)
    local = LocalMap.trusted(
        graph.dim, frame, default_end_pose(frame, ids), np.ascontiguousarray(ids, dtype=np.int64),
        np.full(ids.size, POSE, dtype=np.int8), np.ascontiguousarray(values.reshape(-1), dtype=np.float64),
        block_diagonal(blocks), name=graph.name,
    )
    # The structure holds by construction (distinct poses, none of them the frame, the end pose
    # one of them) and the blocks are symmetric positive definite (the graph checked each edge):
    # what is left are the bounds, checked from the blocks (the pose-graph decoder's hot path).
    # With no edge fused, the estimate is the measurements and the blocks the edges' information:
    # when the graph passed these limits, its checks were the map's bounds, all but the condition
    # number of the whole matrix (a message through the node: 0.08 of its 0.46 ms of decoding).
    try:
        if blocks is graph.information and graph.checked_with(limits):
            check_block_diagonal_condition(blocks, f"local map {local.name!r}", limits)
        else:
            local.check_numbers(limits, blocks=blocks)
    except InvalidMapError as exc:
        raise GraphError(str(exc)) from None
    return local


def fuse_star_edges(graph: PoseGraph) -> tuple[IntArray, FloatArray, FloatArray]:
    """Return the poses of a star graph with repeated edges fused: ids, ``(m, p)`` values and
    ``(m, p, p)`` information blocks, in first-appearance order.

    Edges to one pose are independent observations of it: the fused one has information
    ``I = sum_k I_k`` and value ``I^-1 sum_k I_k z_k``, each repeat's angles taken next to the
    first's (``2 pi`` wrapped) — exactly :func:`linear_slam_ros.core.local_map.fuse_repeated`
    on the block-diagonal information, computed block by block.
    """
    to = graph.to_ids
    uniq, first, inverse = np.unique(to, return_index=True, return_inverse=True)
    if uniq.size == to.size:
        return to.astype(np.int64), graph.measurements, graph.information
    order = np.argsort(first)  # keep first-appearance order
    rank = np.empty_like(order)
    rank[order] = np.arange(order.size)
    target = rank[inverse]  # fused pose index of each edge
    d, p = graph.dim, pose_size(graph.dim)
    z = graph.measurements.copy()
    reference = z[first[order][target]]  # the first edge to the same pose
    z[:, d:] = reference[:, d:] + wrap_angle(z[:, d:] - reference[:, d:])
    info = np.zeros((uniq.size, p, p))
    np.add.at(info, target, graph.information)
    eta = np.zeros((uniq.size, p))
    np.add.at(eta, target, np.einsum("kij,kj->ki", graph.information, z))
    values = np.asarray(np.linalg.solve(info, eta[..., None])[..., 0], dtype=np.float64)
    logger.warning("%s: fused %d repeated variable(s) into one each", graph.name, to.size - uniq.size)
    return to[first[order]].astype(np.int64), values, 0.5 * (info + np.swapaxes(info, 1, 2))


def block_diagonal(blocks: FloatArray) -> InfoMatrix:
    """Return the block-diagonal matrix of ``(m, p, p)`` blocks: dense up to ``DENSE_MAX``
    scalars, CSR above (built from the blocks' entries, never densified)."""
    m, p, _ = blocks.shape
    n = m * p
    if n <= DENSE_MAX:
        dense = np.zeros((m, p, m, p))
        dense[np.arange(m), :, np.arange(m), :] = blocks
        return dense.reshape(n, n)
    index = np.arange(n).reshape(m, p)
    rows = np.repeat(index, p, axis=1).ravel()  # block b, row i, column j -> b*p + i
    cols = np.tile(index, (1, p)).ravel()  # -> b*p + j
    matrix = sp.csr_matrix((blocks.ravel(), (rows, cols)), shape=(n, n))
    matrix.eliminate_zeros()  # the structure sp.csr_matrix(dense) would have
    return matrix


def _checked_map(
    dim: int, frame: int, end: int | None, ids: IntArray, kinds: npt.NDArray[np.int8], x: FloatArray, info: InfoMatrix,
    name: str,
    limits: InputLimits | None,
) -> LocalMap:
    """Return a local map validated with ``limits``; an invalid one raises :class:`GraphError`."""
    local = LocalMap.trusted(
        dim, frame, end, np.ascontiguousarray(ids, dtype=np.int64), np.ascontiguousarray(kinds, dtype=np.int8),
        np.ascontiguousarray(x, dtype=np.float64), info, name=name,
    )
    try:
        local.validate(limits)
    except InvalidMapError as exc:
        raise GraphError(str(exc)) from None
    return local


def lago_local_map(graph: PoseGraph, limits: InputLimits | None = None) -> LocalMap:
    """Return the pose-only local map of a 2D graph by LAGO, in its first edge's ``from`` frame.

    Args:
        graph: a connected 2D graph.
        limits: the numeric bounds the map is validated with (default limits when None).

    Returns:
        Every other pose of the graph estimated by :func:`linear_slam_ros.pose_graph.lago.lago`
        anchored at ``from_ids[0]``; the end pose is the last of the odometry chain from there
        (:func:`chunk_end_pose`, None when the chain is empty); the name is the graph's with
        ``" (LAGO)"``.

    Raises:
        GraphError: the graph is 3D, or disconnected, or its map is invalid.
    """
    if graph.dim != 2:
        raise GraphError(f"{graph.name}: LAGO is 2D only; this chunk is {graph.dim}D and not a star")
    frame = int(graph.from_ids[0])
    result = lago(graph, anchor_id=frame).map
    end = chunk_end_pose(graph.from_ids, graph.to_ids, frame)
    return _checked_map(
        2, frame, end if end != frame else None, result.ids, result.kinds, result.x, result.info,
        f"{graph.name} (LAGO)", limits,
    )


def chunk_to_local_map(graph: PoseGraph, limits: InputLimits | None = None) -> LocalMap:
    """Return the pose-only local map of a graph, in the frame of its first edge's ``from`` pose.

    Star graphs convert exactly (:func:`star_chunk_to_local_map`); other 2D graphs go through
    LAGO (:func:`lago_local_map`). The map is validated with ``limits`` (default limits when
    None).

    Raises:
        GraphError: the graph cannot be converted (the message says why).
    """
    if graph.is_star:
        return star_chunk_to_local_map(graph, limits)
    return lago_local_map(graph, limits)


def edge_maps(graph: PoseGraph) -> list[LocalMap]:
    """Return each edge as a one-pose local map (for χ² and Gauss-Newton on the graph objective).

    Args:
        graph: any graph.

    Returns:
        One map per edge, in edge order: pose ``to_ids[e]`` in the frame of pose
        ``from_ids[e]`` (also its end pose), estimate ``measurements[e]``, information
        ``information[e]``, named ``edge_<e>``.
    """
    maps = []
    for e in range(graph.n_edges):
        maps.append(
            LocalMap.trusted(
                graph.dim, int(graph.from_ids[e]), int(graph.to_ids[e]), graph.to_ids[e : e + 1].copy(),
                np.array([POSE], dtype=np.int8), graph.measurements[e].copy(), graph.information[e], f"edge_{e}",
            )
        )
    return maps


def graph_from_local_maps(maps: Sequence[LocalMap]) -> PoseGraph:
    """Rebuild a pose graph from pose-only local maps (2D or 3D).

    Args:
        maps: maps of one dimension holding only poses.

    Returns:
        The graph of every map's edges, in map order: from the map's frame pose to each of its
        poses, the pose's estimate as the measurement and the diagonal block of the map's
        information as the edge's (cross terms dropped).

    Raises:
        GraphError: a map holds features or differs in dimension from the first, or the edges
            make an invalid graph.
    """
    f, t, z, info = [], [], [], []
    dim = maps[0].dim if maps else 2
    for m in maps:
        if m.dim != dim or np.any(m.kinds != POSE):
            raise GraphError(f"map {m.name!r} is not a {dim}D pose-only map")
        dense = m.info_dense()
        for i in range(m.n_vars):
            sl = m.scalar_slice(i)
            f.append(m.frame_id)
            t.append(int(m.ids[i]))
            z.append(m.x[sl])
            info.append(dense[sl, sl])
    p = pose_size(dim)
    return PoseGraph.from_edges(f, t, np.array(z).reshape(-1, p), np.array(info).reshape(-1, p, p), dim=dim)


def star_local_maps(graph: PoseGraph, limits: InputLimits | None = None) -> list[LocalMap]:
    """Split a graph (2D or 3D) into pose-only local maps, one star per pose edges leave.

    This is how Linear SLAM joins a pose graph (a g2o file): the edges leaving pose ``i`` are
    a local map in the frame of pose ``i`` (:func:`star_chunk_to_local_map`, repeated edges
    fused), and the maps are joined in increasing ``i``, as the benchmark pose-only datasets
    are. The graph objective is the sum of the maps' χ² (up to the constant of fused repeats).
    A star whose frame pose no edge from an earlier pose reaches (odometry written backwards,
    ``EDGE k+1 k``) could never join: its edges to earlier poses are first turned round
    (:func:`forward_edges`).

    Args:
        graph: any graph; poses that no edge leaves are reached from other stars.
        limits: the numeric bounds the maps are validated with (default limits when None).

    Returns:
        The maps, by increasing frame pose, named ``"<graph name>: edges from pose <i>"``; each
        ends at the next map's frame pose when it holds it (else at
        :func:`~linear_slam_ros.core.local_map.default_end_pose`).

    Raises:
        GraphError: a map is invalid.
    """
    from_ids, to_ids, measurements, information = forward_edges(graph)
    order = np.argsort(from_ids, kind="stable")
    frames, starts = np.unique(from_ids[order], return_index=True)
    bounds = np.append(starts, order.size)
    maps = []
    for k, frame in enumerate(frames.tolist()):
        edges = order[bounds[k] : bounds[k + 1]]
        star = PoseGraph.from_edges(
            from_ids[edges], to_ids[edges], measurements[edges], information[edges],
            dim=graph.dim, name=f"{graph.name}: edges from pose {frame}", limits=limits,
        )
        maps.append(star_chunk_to_local_map(star, limits))
    # Each star ends at the next star's frame pose when it holds it: that is the pose the next one joins at.
    # The default (the frame's successor, else the largest id) took a loop closure's pose for the end when
    # poses are not numbered 0, 1, 2, ... (a g2o file with ids 0, 2, 4, ..., two sessions apart), and the
    # divide-and-conquer joins then found no shared frame.
    for k in range(len(maps) - 1):
        following = maps[k + 1].frame_id
        if maps[k].end_id != following and maps[k].has_pose(following):
            maps[k] = maps[k].replace(end_id=following)
    return maps


def forward_edges(graph: PoseGraph) -> tuple[IntArray, IntArray, FloatArray, FloatArray]:
    """Return a graph's edges, those to an earlier pose from a pose no edge from an earlier pose reaches turned round.

    Stars are joined by increasing frame pose, so star ``i`` joins when an earlier star holds pose
    ``i``. When no edge ``j -> i`` with ``j < i`` exists, its edges to earlier poses are turned
    round, and star ``j`` holds ``i`` then; other edges are left as they are (a backward loop
    closure from a pose the odometry reaches stays in its star, as before). Edge ``i -> j``
    becomes ``j -> i``: the measurement is inverted
    (``z⁻¹ = (R (0 - t), angles(Rᵀ))``, pose ``i`` seen from pose ``j``) and its information moved to
    first order at the measurement, ``I' = G⁻ᵀ I G⁻¹`` with ``G = ∂z⁻¹/∂z`` (exact Jacobians of
    :func:`~linear_slam_ros.core.geometry.poses_to_frame`). Turning round twice gives the edge back.

    Returns:
        ``(from_ids, to_ids, measurements, information)``.
    """
    backward = graph.from_ids > graph.to_ids
    reached = graph.to_ids[~backward]  # poses an edge from an earlier pose reaches
    back = np.flatnonzero(backward & ~np.isin(graph.from_ids, reached))
    if not back.size:  # every star joins as it is: the graph's own arrays
        return graph.from_ids, graph.to_ids, graph.measurements, graph.information
    from_ids, to_ids = graph.from_ids.copy(), graph.to_ids.copy()
    measurements, information = graph.measurements.copy(), graph.information.copy()
    d, z = graph.dim, graph.measurements[back]
    inverse = poses_to_frame(d, z[:, :d], z[:, d:], np.zeros_like(z[:, :d]), np.zeros_like(z[:, d:]))
    g_inv = np.linalg.inv(inverse.d_frame)
    info = np.swapaxes(g_inv, 1, 2) @ graph.information[back] @ g_inv
    from_ids[back], to_ids[back] = graph.to_ids[back], graph.from_ids[back]
    measurements[back] = np.concatenate([inverse.translations, inverse.angles], 1)
    information[back] = 0.5 * (info + np.swapaxes(info, 1, 2))
    logger.info("%s: %d edge(s) to an earlier pose turned round", graph.name, back.size)
    return from_ids, to_ids, measurements, information


def chunk_end_pose(from_ids: IntArray, to_ids: IntArray, frame: int) -> int:
    """Return the last pose of the odometry chain ``frame, frame + 1, ...`` present in the edges.

    Args:
        from_ids, to_ids: ``(m,)`` the edges' pose ids (either direction counts).
        frame: the chain's first pose.

    Returns:
        The last pose ``end`` such that every ``(k, k + 1)`` for ``frame <= k < end`` is an
        edge; ``frame`` itself when ``(frame, frame + 1)`` is not.
    """
    pairs = {(min(a, b), max(a, b)) for a, b in zip(from_ids.tolist(), to_ids.tolist(), strict=True)}
    end = frame
    while (end, end + 1) in pairs:
        end += 1
    return end
