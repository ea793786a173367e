r"""Exact maximum-weight k-clique: the combinatorial core of view selection.

The supplement ("View Selection") picks the supporting views ``V_s`` among candidates ``V_c`` as

.. math::

    \max_{V_s \subset V_c,\ |V_s| = k}
    \sum_{i \in V_s} w_i + \sum_{\{i, j\} \subset V_s} W_{ij}

with node weights ``w_i = s_iR ξ_iR`` and edge weights ``W_ij = λ s_ij ξ_ij``, over the k-subsets
that are cliques of the graph joining candidates that co-observe enough voxels.

Algorithm (exact): every k-clique lies inside some maximal clique, so the maximal cliques are
enumerated with :func:`networkx.find_cliques` (Bron–Kerbosch with pivoting), sorted by an upper
bound on their best k-subset (the ``k`` largest node weights plus the ``k(k-1)/2`` largest edge
weights inside them), and the k-subsets of each are scored in one vectorised numpy gather until
the bound of the next maximal clique cannot beat the best value found. The cost grows with the
number of k-subsets of the maximal cliques, ``O(C(n, k))`` for a complete graph on ``n`` nodes:
callers cap ``n`` (:class:`vadgs.select.ViewSelectionConfig` ``max_candidates``, default 24,
``C(24, 4) = 10626`` subsets, well under a millisecond to score).

**Bounded.** Before any subset is scored, the work is counted: the maximal cliques (at most
:data:`MAX_CLIQUES`; their enumeration stops there) and the k-subsets they hold,
``sum C(|c|, k)``. Beyond ``max_subsets`` (default :data:`MAX_SUBSETS`, 2 million: a few seconds
at ``k = 10``, 1-3 µs per subset) the call raises a :class:`ValueError` naming the counts, within a
second, instead of running for minutes (``n = 40, k = 10`` on a complete graph holds
``8.5e8`` subsets: it used 21 GB before this check). The subsets are generated in chunks of
65536, so memory stays at a few MB whatever the count. There is no approximate fallback: lower
``k`` or the candidates, or pass a larger ``max_subsets`` knowingly.
"""

from __future__ import annotations

import itertools
import math
from typing import NamedTuple

import networkx as nx
import numpy as np
import torch

from vadgs.checks import check_finite, check_shape

__all__ = ["MAX_CLIQUES", "MAX_SUBSETS", "Clique", "max_weight_clique"]

_CHUNK = 1 << 16  # k-subsets scored per numpy batch

#: Default cap on the k-subsets :func:`max_weight_clique` scores (it refuses beyond).
MAX_SUBSETS = 2_000_000
#: Cap on the maximal cliques enumerated (a graph with more is refused).
MAX_CLIQUES = 50_000


class Clique(NamedTuple):
    """A maximum-weight clique.

    Attributes:
        nodes: ``(s,)`` int64 node ids in increasing order, ``s = min(k, ω)`` with ``ω`` the
            size of the largest clique of the graph (``0`` for an empty graph).
        weight: the objective value of ``nodes`` (``0.0`` when empty).
    """

    nodes: torch.Tensor
    weight: float


def _combination_chunks(m: int, s: int):
    """The ``s``-subsets of ``range(m)`` as ``(<= _CHUNK, s)`` int64 arrays, in lexicographic order."""
    it = itertools.combinations(range(m), s)
    while True:
        flat = np.fromiter(itertools.chain.from_iterable(itertools.islice(it, _CHUNK)), dtype=np.int64)
        if flat.size == 0:
            return
        yield flat.reshape(-1, s)


def _subset_weights(subsets: np.ndarray, w: np.ndarray, W: np.ndarray) -> np.ndarray:
    """Objective of each row of ``subsets (C, s)``; ``W`` symmetric with a zero diagonal."""
    node = w[subsets].sum(1)
    edge = W[subsets[:, :, None], subsets[:, None, :]].sum((1, 2)) / 2
    return node + edge


def max_weight_clique(
    node_weight: torch.Tensor,
    edge_weight: torch.Tensor,
    k: int,
    adjacency: torch.Tensor | None = None,
    max_subsets: int = MAX_SUBSETS,
) -> Clique:
    """Find the k-clique maximising the sum of its node weights and its edge weights. Exact.

    When the graph has no clique of size ``k`` (fewer than ``k`` nodes, or too few edges), the
    best clique of the largest size ``ω < k`` that exists is returned instead: check
    ``len(result.nodes)``. Ties are broken deterministically (the same input gives the same
    answer). The search runs on the CPU in float64; ``nodes`` is returned on the input's device.
    Not differentiable.

    Args:
        node_weight: ``(n,)`` node weights ``w_i`` (any sign).
        edge_weight: ``(n, n)`` edge weights ``W_ij``; symmetrised as ``(W + W^T) / 2``, the
            diagonal is ignored.
        k: the clique size wanted, ``>= 1``.
        adjacency: optional ``(n, n)`` bool, the graph (symmetrised with ``or``; diagonal
            ignored). ``None`` means the complete graph.
        max_subsets: refuse a graph whose maximal cliques hold more k-subsets than this (the
            work bound of the module docstring).

    Returns:
        A :class:`Clique`.

    Raises:
        ValueError: on bad shapes, ``k < 1``, non-finite weights (a value check), or a search
            beyond ``max_subsets`` subsets or :data:`MAX_CLIQUES` maximal cliques.

    Example:
        >>> w = torch.tensor([1.0, 2.0, 1.0, 5.0])
        >>> W = torch.zeros(4, 4); W[0, 1] = W[1, 0] = 3.0
        >>> adj = torch.ones(4, 4, dtype=torch.bool); adj[0, 3] = adj[3, 0] = False
        >>> max_weight_clique(w, W, 2, adj)  # {1, 3}: 2 + 5 beats {0, 1}: 1 + 2 + 3
        Clique(nodes=tensor([1, 3]), weight=7.0)
        >>> max_weight_clique(w, W, 3, adj)  # {0, 1, 2}: 7, {1, 2, 3}: 8
        Clique(nodes=tensor([1, 2, 3]), weight=8.0)
        >>> max_weight_clique(w, W, 5, adj).nodes  # no 5-clique: the best of the largest (3)
        tensor([1, 2, 3])
    """
    dims = check_shape(node_weight, "node_weight", ("n",))
    check_shape(edge_weight, "edge_weight", ("n", "n"), dims)
    if adjacency is not None:
        check_shape(adjacency, "adjacency", ("n", "n"), dims)
    if int(k) < 1:
        raise ValueError(f"k: expected a clique size >= 1, got {k}")
    check_finite(node_weight, "node_weight")
    check_finite(edge_weight, "edge_weight")
    n, device = dims["n"], node_weight.device
    empty = Clique(torch.zeros(0, dtype=torch.long, device=device), 0.0)
    if n == 0:
        return empty
    w = node_weight.detach().cpu().double().numpy()
    W = edge_weight.detach().cpu().double().numpy()
    W = (W + W.T) / 2
    np.fill_diagonal(W, 0.0)
    if adjacency is None:
        adj = np.ones((n, n), dtype=bool)
    else:
        adj = adjacency.detach().cpu().numpy().astype(bool)
        adj = adj | adj.T
    np.fill_diagonal(adj, False)

    graph = nx.Graph()
    graph.add_nodes_from(range(n))
    rows, cols = np.nonzero(np.triu(adj, 1))
    graph.add_edges_from(zip(rows.tolist(), cols.tolist()))
    cliques: list[np.ndarray] = []
    for c in nx.find_cliques(graph):
        if len(cliques) == MAX_CLIQUES:
            raise ValueError(
                f"max_weight_clique: the graph of {n} nodes has more than MAX_CLIQUES = {MAX_CLIQUES} "
                "maximal cliques; the exact search is refused (fewer candidates or a sparser adjacency)"
            )
        cliques.append(np.array(sorted(c), dtype=np.int64))
    size = min(int(k), max(len(c) for c in cliques))
    cliques = [c for c in cliques if len(c) >= size]
    work = sum(math.comb(len(c), size) for c in cliques)
    if work > max_subsets:
        raise ValueError(
            f"max_weight_clique: k = {size} over {n} nodes ({len(cliques)} maximal clique(s), the largest "
            f"of {max(len(c) for c in cliques)}) means {work:.3g} subsets to score, more than "
            f"max_subsets = {max_subsets:.3g}; lower k or the number of candidates, or raise max_subsets"
        )

    # upper bound on the best size-subset of each maximal clique: top node + top edge weights
    num_pairs = size * (size - 1) // 2
    bounds = []
    for c in cliques:
        top_nodes = np.sort(w[c])[-size:].sum()
        if num_pairs:
            sub = W[np.ix_(c, c)][np.triu_indices(len(c), 1)]
            top_nodes += np.sort(sub)[-num_pairs:].sum()
        bounds.append(top_nodes)
    order = np.argsort(-np.asarray(bounds), kind="stable")

    best_val, best_nodes = -np.inf, None
    for ci in order:
        if bounds[ci] <= best_val:
            break  # sorted by bound: no later clique can do better
        c = cliques[ci]
        for combos in _combination_chunks(len(c), size):
            subsets = c[combos]
            vals = _subset_weights(subsets, w, W)
            i = int(np.argmax(vals))
            if vals[i] > best_val:
                best_val, best_nodes = float(vals[i]), subsets[i]
    assert best_nodes is not None  # at least one clique of ``size`` exists
    return Clique(torch.as_tensor(np.sort(best_nodes), device=device), best_val)
