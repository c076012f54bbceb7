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
block; each frame's mean given the tail (``A_i``, ``d x D``) is kept only until
the last frame that needs it is done, and ``A_i Sigma_TT A_i^T`` is one
matrix product per batch of frames (``_backward``), so a pass costs
O(N d D^2) time (mostly in those batched products) and O(d D) memory beyond
the N outputs, instead of one Bayes-tree marginal per pose.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
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


def _tail_sqrt_covariance(
    conds: Sequence[Conditional], dims: dict[int, int]
) -> tuple[dict[int, int], np.ndarray]:
    """(offset of each tail variable, R_T^-1) from the tail's conditionals: the tail's
    covariance is ``R_T^-1 R_T^-T``."""
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
    return offset, (np.linalg.solve(R, np.eye(total)) if total else R)


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
    k = node.parents.index(c.key)
    a = sum(map(dims.__getitem__, node.parents[:k]))
    b = a + dims[c.key]
    if node.parents[:k] + node.parents[k + 1 :] == c.parents:  # same order: drop c's columns
        S_top = np.concatenate([node.S[:, :a], node.S[:, b:]], axis=1)
    else:
        cols: dict[int, tuple[int, int]] = {}
        col = 0
        for p in node.parents:
            cols[p] = (col, col + dims[p])
            col += dims[p]
        S_top = np.concatenate([node.S[:, cols[p][0] : cols[p][1]] for p in c.parents], axis=1)
    d0, d1 = node.R.shape[0], c.R.shape[0]
    R = np.zeros((d0 + d1, d0 + d1))
    R[:d0, :d0] = node.R
    R[:d0, d0:] = node.S[:, a:b]
    R[d0:, d0:] = c.R
    S = np.vstack([S_top, c.S]) if S_top.size else np.zeros((d0 + d1, 0))
    return _Node(node.keys + [c.key], node.dims + [d1], R, c.parents, S)


def _merges(last: _Node, c: Conditional) -> bool:
    """Whether ``c`` is ``last``'s parent and their other parents agree."""
    if len(last.parents) != len(c.parents) + 1 or c.key not in last.parents:
        return False
    k = last.parents.index(c.key)
    rest = last.parents[:k] + last.parents[k + 1 :]
    return rest == c.parents or set(rest) == set(c.parents)


def _nodes(conds: Sequence[Conditional], dims: dict[int, int]) -> list[_Node]:
    """Supernodes: a conditional merged with the next when that is its parent and the
    remaining parents agree (a frame's pose and velocity)."""
    nodes: list[_Node] = []
    for c in conds:
        if nodes and _merges(nodes[-1], c):
            nodes[-1] = _merge(nodes[-1], c, dims)
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
    parents = node.parents
    in_tail = tuple(map(offset.__contains__, parents))
    signature = (
        in_tail,
        tuple(map(dims.__getitem__, parents)),
        tuple(filter(offset.__contains__, parents)),
    )
    hit = cache.get(signature)
    if hit is None:
        s_cols, tail_idx, free_cols, col = [], [], [], 0
        for k, p in enumerate(parents):
            if in_tail[k]:
                s_cols += range(col, col + dims[p])
                tail_idx += range(offset[p], offset[p] + dims[p])
            else:
                free_cols.append((k, col, dims[p]))
            col += dims[p]
        hit = (np.asarray(s_cols, np.int64), np.asarray(tail_idx, np.int64), free_cols)
        cache[signature] = hit
    s_cols, node.tail_idx, free_cols = hit
    node.S_tail = node.S[:, s_cols]
    free: dict[int, np.ndarray] = {}
    for k, col, dp in free_cols:
        j, o = where[parents[k]]
        block = free.setdefault(j, np.zeros((node.R.shape[0], node_dim[j])))
        block[:, o : o + dp] = node.S[:, col : col + dp]
    node.free = list(free.items())


# Nodes whose tail rows wait for one matrix product with the tail's square root.
_BATCH = 256


class _TailProducts:
    """``A_i Sigma_TT A_i^T`` of many nodes, as one product ``A @ R_T^-1`` per batch.

    With ``prior_rows`` ((D, P) rows of ``R_T^-1`` at the priors' P coordinates,
    transposed) and ``prior_info`` ((P, P) their information) also ``C_i prior_info
    C_i^T`` into ``share``, ``C_i = W_i prior_rows = Sigma_iP`` (``W_i = A_i R_T^-1``):
    see ``selected_covariances_and_shares``.
    """

    def __init__(
        self,
        tail_rinv: np.ndarray,
        diag: dict[int, np.ndarray],
        prior_rows: np.ndarray | None = None,
        prior_info: np.ndarray | None = None,
        share: dict[int, np.ndarray] | None = None,
    ):
        self.tail_rinv = tail_rinv
        self.diag = diag
        self.prior_rows = prior_rows
        self.prior_info = prior_info
        self.share = share
        self.pending: list[tuple[int, np.ndarray]] = []

    def add(self, i: int, A: np.ndarray) -> None:
        self.pending.append((i, A))
        if len(self.pending) >= _BATCH:
            self.flush()

    def flush(self) -> None:
        by_dim: dict[int, list[tuple[int, np.ndarray]]] = {}
        for i, A in self.pending:
            by_dim.setdefault(A.shape[0], []).append((i, A))
        self.pending = []
        for d, items in by_dim.items():
            W = (np.concatenate([A for _, A in items]) @ self.tail_rinv).reshape(len(items), d, -1)
            outer = W @ W.transpose(0, 2, 1)
            for (i, _), o in zip(items, outer, strict=True):
                q = self.diag[i] + o
                self.diag[i] = 0.5 * (q + q.T)
            if self.share is not None:
                C = W @ self.prior_rows  # (n, d, P): Sigma_iP
                part = C @ self.prior_info @ C.transpose(0, 2, 1)
                for (i, _), o in zip(items, part, strict=True):
                    self.share[i] = 0.5 * (o + o.T)


def _backward(
    nodes: list[_Node],
    tail_rinv: np.ndarray,
    wanted_nodes: set[int],
    prior_rows: np.ndarray | None = None,
    prior_info: np.ndarray | None = None,
    share: dict[int, np.ndarray] | None = None,
) -> dict[int, np.ndarray]:
    """Each wanted node's marginal covariance, last node first (see the module docstring).

    Split by the tail T: ``x_i = A_i x_T + e_i`` with ``e`` independent of
    ``x_T``, so ``Sigma_ii = Q_ii + A_i Sigma_TT A_i^T`` (``Q = Cov(e)``).
    Backwards, with B_ij = R_i^-1 S_ij over the free parents j:

        A_i  = -R_i^-1 (S_iT + sum_j S_ij A_j)
        Q_ig = -sum_j B_ij Q_jg          (g a free parent of i)
        Q_ii =  R_i^-1 R_i^-T + sum_jk B_ij Q_jk B_ik^T

    The sequential part is d x D and d x d products; the D x D work is one
    product per batch of nodes with ``R_T^-1`` (``Sigma_TT = R_T^-1 R_T^-T``).
    """
    first_child: dict[int, int] = {}
    for i, nd in enumerate(nodes):
        for j, _ in nd.free:
            first_child.setdefault(j, i)  # nodes are visited in order: the first is the min
    done_at: dict[int, list[int]] = {}
    for j, i in first_child.items():
        done_at.setdefault(i, []).append(j)
    D = tail_rinv.shape[0]
    A_of: dict[int, np.ndarray] = {}  # node -> (d, D) E[x_node | x_T] = A x_T
    Q: dict[int, np.ndarray] = {}
    pair: dict[tuple[int, int], np.ndarray] = {}  # (i, j), i < j
    pairs_of: dict[int, list[tuple[int, int]]] = {}
    diag: dict[int, np.ndarray] = {}
    tail = _TailProducts(tail_rinv, diag, prior_rows, prior_info, share)

    def get(a: int, b: int) -> np.ndarray:
        if a == b:
            return Q[a]
        return pair[(a, b)] if a < b else pair[(b, a)].T

    def drop(j: int) -> None:
        A_of.pop(j, None)
        Q.pop(j, None)
        for ab in pairs_of.pop(j, []):
            pair.pop(ab, None)

    for i in range(len(nodes) - 1, -1, -1):
        nd = nodes[i]
        d = nd.R.shape[0]
        Rinv = np.linalg.inv(nd.R)
        M = np.zeros((d, D))
        M[:, nd.tail_idx] = nd.S_tail
        B = []
        for f, Sf in nd.free:
            M += Sf @ A_of[f]
            B.append((f, Rinv @ Sf))
        A = -Rinv @ M
        q = Rinv @ Rinv.T
        for g, Bg in B:
            m = sum(Bf @ get(f, g) for f, Bf in B)
            pair[(i, g)] = -m
            pairs_of.setdefault(i, []).append((i, g))
            pairs_of.setdefault(g, []).append((i, g))
            q = q + m @ Bg.T
        A_of[i], Q[i] = A, q
        if i in wanted_nodes:
            diag[i] = q
            tail.add(i, A)
        for j in done_at.get(i, []):
            drop(j)
        if i not in first_child:
            drop(i)
    tail.flush()
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
    return selected_covariances_and_shares(conditionals, tail_start, wanted, {})[0]


def selected_covariances_and_shares(
    conditionals: Sequence[Conditional],
    tail_start: int,
    wanted: Sequence[int],
    priors: Mapping[int, np.ndarray],
) -> tuple[dict[int, np.ndarray], dict[int, np.ndarray]]:
    """``selected_covariances`` and each wanted variable's share from some priors.

    A prior ``N(m_k, Lambda_k^-1)`` on a tail variable k moves the solution by
    ``Sigma_ik Lambda_k`` per unit of ``m_k`` (linearised), so a prior mean drawn
    as the prior says (a survey's centres) contributes ``Sigma_iP Lambda_P Sigma_Pi``
    (P: the priors' variables) to variable i's covariance: the error that every
    variable seeing those priors shares. ``Sigma_iP = A_i Sigma_TP`` (module
    docstring), so each share costs one more product per batch of frames.

    Args:
        conditionals, tail_start, wanted: as ``selected_covariances``.
        priors: tail key -> (d, d) information of its prior (``Lambda_k``).

    Returns:
        (key -> (d, d) covariance, key -> (d, d) the priors' share of it; empty
        without ``priors``).
    """
    dims = {c.key: c.R.shape[0] for c in conditionals}
    offset, tail_rinv = _tail_sqrt_covariance(conditionals[tail_start:], dims)
    tail_cov = tail_rinv @ tail_rinv.T
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
    prior_rows, info, share_tail, node_share = None, None, None, None
    if priors:
        idx = np.concatenate([np.arange(offset[k], offset[k] + dims[k]) for k in priors])
        info = np.zeros((len(idx), len(idx)))
        o = 0
        for k, lam in priors.items():
            info[o : o + dims[k], o : o + dims[k]] = lam
            o += dims[k]
        prior_rows = tail_rinv[idx].T  # Sigma_TP = R_T^-1 prior_rows
        cross = tail_cov[:, idx]
        share_tail = cross @ info @ cross.T
        node_share = {}
    diag = _backward(nodes, tail_rinv, {where[k][0] for k in want}, prior_rows, info, node_share)
    out, shares = {}, {}
    for key in wanted:
        d = dims[key]
        if key in offset:
            o = offset[key]
            out[key] = tail_cov[o : o + d, o : o + d].copy()
            if share_tail is not None:
                shares[key] = share_tail[o : o + d, o : o + d].copy()
        else:
            j, o = where[key]
            out[key] = diag[j][o : o + d, o : o + d].copy()
            if node_share is not None:
                shares[key] = node_share[j][o : o + d, o : o + d].copy()
    return out, shares
