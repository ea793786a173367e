"""Maps resampled by an integer factor (vadgs.geometry.resample) against loops over the blocks."""

from __future__ import annotations

import pytest
import torch

from vadgs.geometry.resample import pool_mask, pool_valid, repeat


def _maps(seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    x = torch.randn(3, 9, 10, generator=g, dtype=torch.float64)
    valid = torch.rand(9, 10, generator=g) > 0.4
    return x, valid


class TestRepeat:
    def test_each_pixel_fills_its_block(self):
        x, _ = _maps()
        out = repeat(x, 3)
        assert out.shape == (3, 27, 30)
        for y in range(27):
            for u in range(30):
                assert torch.equal(out[:, y, u], x[:, y // 3, u // 3])
        assert repeat(x, 1) is x

    def test_bad_factor(self):
        with pytest.raises(ValueError, match=r"f: expected an integer >= 1 \(the resampling factor\), got 0"):
            repeat(torch.zeros(2, 2), 0)
        with pytest.raises(ValueError, match=r"got 1\.5"):
            pool_valid(torch.zeros(1, 2, 2), torch.ones(2, 2, dtype=torch.bool), 1.5)


class TestPoolValid:
    @pytest.mark.parametrize("f", [2, 3])
    @pytest.mark.parametrize("unit", [False, True])
    def test_against_block_loops(self, f, unit):
        x, valid = _maps(f)
        out = pool_valid(x, valid, f, unit)
        H, W = 9 // f, 10 // f
        assert out.shape == (3, H, W)
        for i in range(H):
            for j in range(W):
                v = valid[i * f : (i + 1) * f, j * f : (j + 1) * f]
                if v.sum() * 2 < f * f:  # fewer than half valid: zero
                    assert (out[:, i, j] == 0).all()
                    continue
                mean = x[:, i * f : (i + 1) * f, j * f : (j + 1) * f][:, v].mean(1)
                want = mean / mean.norm() if unit else mean
                assert torch.allclose(out[:, i, j], want), (i, j)

    def test_factor_one_masks(self):
        x, valid = _maps()
        assert torch.equal(pool_valid(x, valid, 1), torch.where(valid, x, torch.zeros_like(x)))

    def test_gradient(self):
        x, valid = _maps()
        x = x[:, :4, :4].clone().requires_grad_(True)
        torch.autograd.gradcheck(lambda t: pool_valid(t, valid[:4, :4], 2), (x,))


class TestPoolMask:
    @pytest.mark.parametrize("f", [1, 2, 4])
    def test_against_block_loops(self, f):
        m = torch.rand(2, 8, 12, generator=torch.Generator().manual_seed(f)) > 0.5
        out = pool_mask(m, f)
        assert out.shape == (2, 8 // f, 12 // f) and out.dtype == torch.bool
        for b in range(2):
            for i in range(8 // f):
                for j in range(12 // f):
                    block = m[b, i * f : (i + 1) * f, j * f : (j + 1) * f]
                    assert bool(out[b, i, j]) == (int(block.sum()) * 2 >= f * f)
