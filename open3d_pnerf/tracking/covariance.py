"""Pose covariances from an Open3D pose graph: marginals of the pose-graph Hessian.

Open3D returns no pose covariance. This module rebuilds the Gauss-Newton Hessian
``H = sum_e c_e J_e^T Lambda_e J_e`` from ``pose_graph.edges`` and each edge's information
``Lambda_e`` (the inverse of the edge's covariance), fixes the reference node and reads the 6x6
diagonal blocks of ``H^-1``.

Conventions (order [rotation(3), translation(3)] throughout):

* a node pose ``T`` (camera-to-world) is perturbed on the right, ``T exp(xi)``, so ``xi``
  is expressed in that camera's own frame;
* an edge (source s, target t, transformation X mapping source-camera points into the
  target camera) has the residual ``e = log(T_t^-1 T_s X^-1)``, a twist in the target
  camera frame. This is the frame in which Open3D's RGB-D odometry builds its information
  ``G^T G`` (``G = [-[q]x, I]`` with q the source points moved into the target camera).
"""

from __future__ import annotations

import numpy as np
import open3d as o3d
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components
from scipy.sparse.linalg import splu

from ..camera import adjoint
from ..errors import InputError

# Right-hand sides solved at once when extracting diagonal blocks of H^-1 (memory bound).
_SOLVE_CHUNK = 600


def edge_jacobians(pose_source: np.ndarray, pose_target: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Jacobians (J_s, J_t), each (6, 6), of ``e = log(T_t^-1 T_s X^-1)`` at e = 0.

    With ``T_s exp(xi_s)`` and ``T_t exp(xi_t)``: ``e ~ e0 + J_s xi_s + J_t xi_t`` where
    ``J_s = Ad(T_t^-1 T_s)`` and ``J_t = -I`` (first order; exact when the edge is consistent).
    """
    return adjoint(np.linalg.inv(pose_target) @ pose_source), -np.eye(6)


def pose_graph_hessian(pose_graph: o3d.pipelines.registration.PoseGraph,
                       information: list[np.ndarray] | None = None) -> sp.csc_matrix:
    """(6N, 6N) sparse Gauss-Newton Hessian ``sum_e c_e J_e^T Lambda_e J_e`` of the graph.

    Lambda_e: the edge's ``information`` (Open3D's), or information[e] when given (one (6, 6)
    per edge, in the graph's order). Each edge is weighted by its ``confidence`` (Open3D's
    line-process weight: 1 for certain edges, in (0, 1] for uncertain ones after
    ``global_optimization``).
    """
    n = len(pose_graph.nodes)
    poses = np.stack([np.asarray(node.pose, dtype=np.float64) for node in pose_graph.nodes])
    rows, cols, blocks = [], [], []
    for k, edge in enumerate(pose_graph.edges):
        s, t = edge.source_node_id, edge.target_node_id
        if not (0 <= s < n and 0 <= t < n) or s == t:
            raise InputError(f"pose_graph.edges[{k}] joins nodes {s} -> {t}; need two distinct nodes of {n}")
        info = edge.confidence * np.asarray(edge.information if information is None else information[k], np.float64)
        jac = dict(zip((s, t), edge_jacobians(poses[s], poses[t])))
        for a in (s, t):
            for b in (s, t):
                rows.append(a)
                cols.append(b)
                blocks.append(jac[a].T @ info @ jac[b])
    return block_matrix(rows, cols, blocks, n)


def block_matrix(rows: list[int], cols: list[int], blocks: list[np.ndarray], n: int) -> sp.csc_matrix:
    """(6n, 6n) sparse matrix, the sum of the (6, 6) `blocks` placed at block row rows[k], block
    column cols[k] (several blocks at one place add up)."""
    if not blocks:
        return sp.csc_matrix((6 * n, 6 * n))
    block_r, block_c = np.meshgrid(np.arange(6), np.arange(6), indexing="ij")
    r = (6 * np.asarray(rows)[:, None, None] + block_r).ravel()
    c = (6 * np.asarray(cols)[:, None, None] + block_c).ravel()
    return sp.coo_matrix((np.stack(blocks).ravel(), (r, c)), shape=(6 * n, 6 * n)).tocsc()  # COO -> CSC sums


def pose_graph_covariances(
    pose_graph: o3d.pipelines.registration.PoseGraph, reference: int = 0, information: list[np.ndarray] | None = None,
    nodes=None,
) -> np.ndarray:
    """(N, 6, 6) float64 covariances of the node poses, [rotation (rad^2), translation (m^2)]
    (nodes: only these are computed, the others left zero; default all).

    The 6x6 diagonal blocks of ``H^-1`` with the reference node held fixed (its covariance is
    zero). ``H`` is :func:`pose_graph_hessian` of the edges' `information`: one (6, 6) per edge,
    the inverse of each edge's covariance (default: each edge's own ``information``); the
    perturbation is ``T exp(xi)`` (camera frame). Every node must be connected to the
    reference through edges, otherwise InputError names the unconnected nodes.
    """
    n = len(pose_graph.nodes)
    if not 0 <= reference < n:
        raise InputError(f"reference must be a node index in [0, {n}), got {reference}")
    if information is not None and len(information) != len(pose_graph.edges):
        raise InputError(f"information has {len(information)} matrices for {len(pose_graph.edges)} edges")
    hessian = pose_graph_hessian(pose_graph, information)
    _check_connected(pose_graph, n, reference)
    covariances = np.zeros((n, 6, 6))
    free = np.array([i for i in range(n) if i != reference], dtype=int)
    wanted = np.flatnonzero(np.isin(free, np.arange(n) if nodes is None else np.asarray(nodes, int)))
    if wanted.size == 0:
        return covariances
    keep = (6 * free[:, None] + np.arange(6)).ravel()
    try:
        lu = splu(hessian[keep][:, keep].tocsc())
    except RuntimeError:  # "Factor is exactly singular"
        raise InputError(
            "the pose-graph Hessian is singular: some node's pose is not fully constrained "
            "(an edge information matrix is rank-deficient or zero)"
        ) from None
    dim = keep.size
    columns = (6 * wanted[:, None] + np.arange(6)).ravel()  # the wanted nodes' rows/columns of the reduced H
    for start in range(0, columns.size, _SOLVE_CHUNK):
        chunk = columns[start : start + _SOLVE_CHUNK]
        rhs = np.zeros((dim, chunk.size))
        rhs[chunk, np.arange(chunk.size)] = 1.0
        cols = lu.solve(rhs)
        for k in range(0, chunk.size, 6):
            j = chunk[k] // 6
            block = cols[6 * j : 6 * j + 6, k : k + 6]
            covariances[free[j]] = 0.5 * (block + block.T)
    return covariances


def _check_connected(pose_graph, n: int, reference: int) -> None:
    """Raise InputError naming the nodes with no edge path to the reference node."""
    src = [e.source_node_id for e in pose_graph.edges]
    dst = [e.target_node_id for e in pose_graph.edges]
    adjacency = sp.coo_matrix((np.ones(len(src)), (src, dst)), shape=(n, n))
    _, labels = connected_components(adjacency, directed=False)
    lonely = np.flatnonzero(labels != labels[reference])
    if lonely.size:
        raise InputError(
            f"pose graph nodes {lonely[:10].tolist()}{'...' if lonely.size > 10 else ''} have no "
            f"edge path to the reference node {reference}; their covariance is unbounded"
        )
