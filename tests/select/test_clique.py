from __future__ import annotations

import itertools

import pytest
import torch

from vadgs.select import Clique, max_weight_clique


def _brute_force(w, W, k, adj):
    """Enumerate every k-subset (falling back to smaller sizes); return (best value, all optimal sets)."""
    n = len(w)
    Ws = (W + W.T) / 2
    for size in range(min(k, n), 0, -1):
        best, arg = -float("inf"), []
        for subset in itertools.combinations(range(n), size):
            if not all(adj[i, j] or adj[j, i] for i, j in itertools.combinations(subset, 2)):
                continue
            val = sum(float(w[i]) for i in subset) + sum(
                float(Ws[i, j]) for i, j in itertools.combinations(subset, 2)
            )
            if val > best + 1e-9:
                best, arg = val, [subset]
            elif abs(val - best) <= 1e-9:
                arg.append(subset)
        if arg:
            return best, arg
    return 0.0, [()]


def _random_graph(n, density, seed, negative=False):
    g = torch.Generator().manual_seed(seed)
    w = torch.rand(n, generator=g, dtype=torch.float64)
    W = torch.rand(n, n, generator=g, dtype=torch.float64)
    if negative:
        w, W = w - 0.5, W - 0.5
    adj = torch.rand(n, n, generator=g) < density
    adj = adj | adj.T
    return w, W, adj


class TestMaxWeightClique:
    def test_smoke(self):
        out = max_weight_clique(torch.rand(5), torch.rand(5, 5), 3)
        assert isinstance(out, Clique) and out.nodes.shape == (3,)

    def test_exception(self):
        with pytest.raises(ValueError, match="edge_weight"):
            max_weight_clique(torch.rand(5), torch.rand(4, 4), 3)
        with pytest.raises(ValueError, match="adjacency"):
            max_weight_clique(torch.rand(5), torch.rand(5, 5), 3, torch.ones(5, 4, dtype=torch.bool))
        with pytest.raises(ValueError, match="k: expected"):
            max_weight_clique(torch.rand(5), torch.rand(5, 5), 0)

    def test_cardinality(self):
        assert max_weight_clique(torch.rand(0), torch.rand(0, 0), 4).nodes.shape == (0,)
        assert max_weight_clique(torch.rand(2), torch.rand(2, 2), 4).nodes.shape == (2,)
        nodes = max_weight_clique(torch.rand(6), torch.rand(6, 6), 4).nodes
        assert nodes.dtype == torch.int64 and torch.equal(nodes, nodes.sort().values)

    @pytest.mark.parametrize("seed", range(40))
    def test_equals_brute_force(self, seed):
        n = 4 + seed % 9  # 4..12 nodes
        k = 2 + seed % 4  # 2..5
        density = (0.3, 0.6, 0.9, 1.0)[seed % 4]
        w, W, adj = _random_graph(n, density, seed, negative=seed % 5 == 0)
        out = max_weight_clique(w, W, k, adj)
        best, optimal = _brute_force(w, W, k, adj)
        assert out.weight == pytest.approx(best, abs=1e-9)
        assert tuple(out.nodes.tolist()) in optimal

    def test_complete_graph_default(self):
        w, W, _ = _random_graph(9, 1.0, 123)
        best, optimal = _brute_force(w, W, 4, torch.ones(9, 9, dtype=torch.bool))
        out = max_weight_clique(w, W, 4)
        assert out.weight == pytest.approx(best) and tuple(out.nodes.tolist()) in optimal

    def test_disconnected_graph_returns_largest_available(self):
        w = torch.tensor([1.0, 2.0, 3.0, 4.0])
        adj = torch.zeros(4, 4, dtype=torch.bool)  # no edges at all: single nodes
        out = max_weight_clique(w, torch.zeros(4, 4), 3, adj)
        assert out.nodes.tolist() == [3] and out.weight == 4.0

    def test_deterministic(self):
        w, W, adj = _random_graph(12, 0.7, 7)
        a, b = max_weight_clique(w, W, 4, adj), max_weight_clique(w, W, 4, adj)
        assert torch.equal(a.nodes, b.nodes) and a.weight == b.weight

    def test_float32_input_and_device(self):
        w, W, adj = _random_graph(8, 0.8, 9)
        out = max_weight_clique(w.float(), W.float(), 3, adj)
        assert out.nodes.device == w.device
