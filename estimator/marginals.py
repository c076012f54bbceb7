"""Marginal covariances of many variables in one backward pass over a Gaussian Bayes net.

A Gaussian graph eliminated in some order gives one conditional per variable,
``R_k x_k + S_k x_P(k) = d_k`` (``R_k`` upper triangular, ``P(k)`` the
parents: variables eliminated later), i.e. the square-root information
matrix R of the whole graph, block upper triangular. The covariance is
``Sigma = (R^T R)^-1``; its blocks on the filled graph's edges follow from the
recursion (Takahashi et al. 1973, "selected inversion"), newest variable first:

    Sigma_kP = -R_k^-1 S_k Sigma_PP
    Sigma_kk =  R_k^-1 R_k^-T - Sigma_kP S_k^T R_k^-T

``Sigma_PP`` needs only blocks between parents of k, which by the elimination's
chordality are themselves parent pairs computed earlier in the pass.

The smoother's graphs have a chain of frames (each frame's parents: the next
frame and every landmark) and a dense tail (the landmarks, the bias, the sign
centres) that every frame touches; the tail is inverted once as one dense
block and each frame keeps its row against it (``d x D``) only until the last
frame that needs it is done, so a pass costs O(N d D^2) time and O(d D)
memory beyond the N outputs, instead of one Bayes-tree marginal per pose.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Conditional:
    """One eliminated variable: ``R x_key + S x_parents = d`` (unit noise).

    Attributes:
        key: the frontal variable.
        R: (d, d) upper triangular.
        parents: the parent variables, in the column order of ``S``.
        S: (d, sum of the parents' dimensions).
    """

    key: int
    R: np.ndarray
    parents: tuple[int, ...]
    S: np.ndarray


def _tail_covariance(
    conds: Sequence[Conditional], dims: dict[int, int]
) -> tuple[dict[int, int], np.ndarray]:
    """(offset of each tail variable, dense covariance of the tail) from its conditionals."""
    offset: dict[int, int] = {}
    total = 0
    for c in conds:
        offset[c.key] = total
        total += dims[c.key]
    R = np.zeros((total, total))
    for c in conds:
        o, d = offset[c.key], dims[c.key]
        R[o : o + d, o : o + d] = c.R
        col = 0
        for p in c.parents:
            dp = dims[p]
            R[o : o + d, offset[p] : offset[p] + dp] = c.S[:, col : col + dp]
            col += dp
    Rinv = np.linalg.solve(R, np.eye(total)) if total else R
    return offset, Rinv @ Rinv.T


@dataclass
class _Node:
    """Consecutive conditionals with the same parents, eliminated as one block.

    ``R x_keys + S_tail x_tail[tail_idx] + sum_f S_f x_f = d``: ``free`` holds
    (node index, S_f) for the parents outside the tail.
    """

    keys: list[int]
    dims: list[int]
    R: np.ndarray
    parents: tuple[int, ...]  # the original parent keys, in the column order of S
    S: np.ndarray
    tail_idx: np.ndarray | None = None
    S_tail: np.ndarray | None = None
    free: list[tuple[int, np.ndarray]] | None = None


def _merge(node: _Node, c: Conditional, dims: dict[int, int]) -> _Node:
    """``node`` with the conditional of its parent ``c.key`` appended (same other parents)."""
    cols: dict[int, tuple[int, int]] = {}
    col = 0
    for p in node.parents:
        cols[p] = (col, col + dims[p])
        col += dims[p]
    a, b = cols[c.key]
    if tuple(p for p in node.parents if p != c.key) == c.parents:  # same order: drop c's columns
        S_top = np.concatenate([node.S[:, :a], node.S[:, b:]], axis=1)
    else:
        S_top = np.concatenate([node.S[:, cols[p][0] : cols[p][1]] for p in c.parents], axis=1)
    d0, d1 = node.R.shape[0], c.R.shape[0]
    R = np.zeros((d0 + d1, d0 + d1))
    R[:d0, :d0] = node.R
    R[:d0, d0:] = node.S[:, a:b]
    R[d0:, d0:] = c.R
    S = np.vstack([S_top, c.S]) if S_top.size else np.zeros((d0 + d1, 0))
    return _Node(node.keys + [c.key], node.dims + [d1], R, c.parents, S)


def _nodes(conds: Sequence[Conditional], dims: dict[int, int]) -> list[_Node]:
    """Supernodes: a conditional merged with the next when that is its parent and the
    remaining parents agree (a frame's pose and velocity)."""
    nodes: list[_Node] = []
    for c in conds:
        if nodes:
            last = nodes[-1]
            if c.key in last.parents and set(last.parents) - {c.key} == set(c.parents):
                nodes[-1] = _merge(last, c, dims)
                continue
        nodes.append(_Node([c.key], [dims[c.key]], c.R, c.parents, c.S))
    return nodes


def _split_parents(
    node: _Node,
    dims: dict[int, int],
    offset: dict[int, int],
    where: dict[int, tuple[int, int]],
    node_dim: list[int],
    cache: dict,
) -> None:
    """Fill ``node``'s tail part and its free parents as whole nodes (zeros for absent keys)."""
    signature = tuple(p if p in offset else -dims[p] for p in node.parents)
    hit = cache.get(signature)
    if hit is None:
        s_cols, tail_idx, col = [], [], 0
        for p in node.parents:
            if p in offset:
                s_cols += range(col, col + dims[p])
                tail_idx += range(offset[p], offset[p] + dims[p])
            col += dims[p]
        hit = (np.asarray(s_cols, np.int64), np.asarray(tail_idx, np.int64))
        cache[signature] = hit
    s_cols, node.tail_idx = hit
    node.S_tail = node.S[:, s_cols]
    free: dict[int, np.ndarray] = {}
    col = 0
    for p in node.parents:
        dp = dims[p]
        if p not in offset:
            j, o = where[p]
            block = free.setdefault(j, np.zeros((node.R.shape[0], node_dim[j])))
            block[:, o : o + dp] = node.S[:, col : col + dp]
        col += dp
    node.free = list(free.items())


def _backward(nodes: list[_Node], tail_cov: np.ndarray, wanted_nodes: set[int]) -> dict:
    """Each node's marginal covariance, last node first (see the module docstring)."""
    first_child: dict[int, int] = {}
    for i, nd in enumerate(nodes):
        for j, _ in nd.free:
            first_child.setdefault(j, i)  # nodes are visited in order: the first is the min
    done_at: dict[int, list[int]] = {}
    for j, i in first_child.items():
        done_at.setdefault(i, []).append(j)
    row: dict[int, np.ndarray] = {}  # node -> (d, D) covariance against the tail
    diag: dict[int, np.ndarray] = {}
    pair: dict[tuple[int, int], np.ndarray] = {}  # (i, j), i < j
    pairs_of: dict[int, list[tuple[int, int]]] = {}

    def get(a: int, b: int) -> np.ndarray:
        if a == b:
            return diag[a]
        return pair[(a, b)] if a < b else pair[(b, a)].T

    def drop(j: int) -> None:
        row.pop(j, None)
        for ab in pairs_of.pop(j, []):
            pair.pop(ab, None)
        if j not in wanted_nodes:
            diag.pop(j, None)

    for i in range(len(nodes) - 1, -1, -1):
        nd = nodes[i]
        St, idx = nd.S_tail, nd.tail_idx
        M_tail = St @ tail_cov[idx]
        for f, Sf in nd.free:
            M_tail += Sf @ row[f]
        Rinv = np.linalg.solve(nd.R, np.eye(nd.R.shape[0]))
        K_tail = -Rinv @ M_tail
        acc = K_tail[:, idx] @ St.T
        for g, Sg in nd.free:
            m = St @ row[g][:, idx].T
            for f, Sf in nd.free:
                m += Sf @ get(f, g)
            K = -Rinv @ m
            pair[(i, g)] = K
            pairs_of.setdefault(i, []).append((i, g))
            pairs_of.setdefault(g, []).append((i, g))
            acc += K @ Sg.T
        row[i] = K_tail
        cov = Rinv @ Rinv.T - acc @ Rinv.T
        diag[i] = 0.5 * (cov + cov.T)
        for j in done_at.get(i, []):
            drop(j)
        if i not in first_child:
            drop(i)
    return diag


def selected_covariances(
    conditionals: Sequence[Conditional], tail_start: int, wanted: Sequence[int]
) -> dict[int, np.ndarray]:
    """Marginal covariance of each ``wanted`` variable, in one backward pass.

    Args:
        conditionals: one per variable, in elimination order (a sequential
            elimination's Bayes net); unit noise.
        tail_start: the conditionals from this index on are inverted as one
            dense block (the variables every frame depends on).
        wanted: the variables whose (d, d) marginal covariance is returned.

    Returns:
        key -> (d, d) covariance.
    """
    dims = {c.key: c.R.shape[0] for c in conditionals}
    offset, tail_cov = _tail_covariance(conditionals[tail_start:], dims)
    nodes = _nodes(conditionals[:tail_start], dims)
    where: dict[int, tuple[int, int]] = {}
    for j, nd in enumerate(nodes):
        o = 0
        for key, d in zip(nd.keys, nd.dims, strict=True):
            where[key] = (j, o)
            o += d
    node_dim = [nd.R.shape[0] for nd in nodes]
    cache: dict = {}
    for nd in nodes:
        _split_parents(nd, dims, offset, where, node_dim, cache)
    want = [k for k in wanted if k not in offset]
    diag = _backward(nodes, tail_cov, {where[k][0] for k in want})
    out = {}
    for key in wanted:
        d = dims[key]
        if key in offset:
            o = offset[key]
            out[key] = tail_cov[o : o + d, o : o + d].copy()
        else:
            j, o = where[key]
            out[key] = diag[j][o : o + d, o : o + d].copy()
    return out
