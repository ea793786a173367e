from __future__ import annotations

import pytest
import torch

from vadgs.mvs import (
    MAX_COST,
    bilateral_ncc,
    bilateral_weights,
    ncc_cost_from_stats,
    patch_offsets,
    reference_patch_stats,
    reference_patches,
)


def _ncc_naive(ref, src, wts, min_variance=1e-5):
    """Obviously-correct loop over patches (float64)."""
    out = torch.empty(ref.shape[0], dtype=torch.float64)
    for i in range(ref.shape[0]):
        r, s, w = ref[i].double(), src[i].double(), wts[i].double()
        rm = sum(w[k] * r[k] for k in range(len(r)))
        sm = sum(w[k] * s[k] for k in range(len(s)))
        vr = sum(w[k] * (r[k] - rm) ** 2 for k in range(len(r)))
        vs = sum(w[k] * (s[k] - sm) ** 2 for k in range(len(s)))
        cov = sum(w[k] * (r[k] - rm) * (s[k] - sm) for k in range(len(r)))
        if vr < min_variance or vs < min_variance:
            out[i] = MAX_COST
        else:
            out[i] = min(max(1 - cov / (vr * vs) ** 0.5, 0.0), MAX_COST)
    return out


def _weights_naive(ref, offsets, sigma_s, sigma_c):
    center = next(k for k in range(len(offsets)) if float(offsets[k].norm()) == 0)
    out = torch.empty_like(ref, dtype=torch.float64)
    for i in range(ref.shape[0]):
        for k in range(ref.shape[1]):
            ds = float((offsets[k] ** 2).sum())
            dc = float(ref[i, k] - ref[i, center]) ** 2
            out[i, k] = torch.exp(
                torch.tensor(-ds / (2 * sigma_s**2) - dc / (2 * sigma_c**2), dtype=torch.float64)
            )
        out[i] /= out[i].sum()
    return out


class TestPatchOffsets:
    def test_cardinality(self):
        assert patch_offsets(5, 2).shape == (36, 2)
        assert patch_offsets(5, 1).shape == (121, 2)
        assert patch_offsets(2, 1)[12].tolist() == [0.0, 0.0]

    def test_symmetric(self):
        off = patch_offsets(5, 2)
        assert torch.allclose(off.mean(0), torch.zeros(2))
        assert off.abs().max() == 5

    def test_exception(self):
        with pytest.raises(ValueError, match="radius"):
            patch_offsets(-1)
        with pytest.raises(ValueError, match="step"):
            patch_offsets(3, 0)


class TestReferencePatches:
    def test_against_loop(self):
        img = torch.rand(2, 1, 7, 9)
        off = patch_offsets(2, 1)
        got = reference_patches(img, off)  # (B, S, P)
        assert got.shape == (2, 25, 63)
        for b in range(2):
            for v in range(7):
                for u in range(9):
                    for k, (dx, dy) in enumerate(off.long().tolist()):
                        x, y = min(max(u + dx, 0), 8), min(max(v + dy, 0), 6)
                        assert got[b, k, v * 9 + u] == img[b, 0, y, x]

    def test_exception(self):
        with pytest.raises(ValueError, match="gray"):
            reference_patches(torch.rand(1, 3, 5, 5), patch_offsets(1))


class TestBilateralWeights:
    def test_against_loop(self):
        off = patch_offsets(2, 1)
        ref = torch.rand(5, 25)
        got = bilateral_weights(ref, off, 2.0, 0.2)
        assert torch.allclose(got.double(), _weights_naive(ref, off, 2.0, 0.2), atol=1e-6)

    def test_sample_axis(self):
        off = patch_offsets(1)
        ref = torch.rand(2, 9, 4)
        a = bilateral_weights(ref, off, 1.0, 0.2, dim=1)
        b = bilateral_weights(ref.transpose(1, 2), off, 1.0, 0.2).transpose(1, 2)
        assert torch.allclose(a, b)
        assert torch.allclose(a.sum(1), torch.ones(2, 4))

    def test_edge_preserving(self):
        off = patch_offsets(1)
        ref = torch.tensor([[0.0, 0.0, 1.0, 0.0, 0.0, 1.0, 0.0, 0.0, 1.0]])  # centre 0, right column 1
        w = bilateral_weights(ref, off, 1.0, 0.2)
        assert w[0, 2] < 0.01 * w[0, 0]

    def test_exception(self):
        with pytest.raises(ValueError, match="ref_patches"):
            bilateral_weights(torch.rand(3, 8), patch_offsets(1), 1.0, 0.2)


class TestBilateralNCC:
    def test_identical_is_zero(self):
        ref = torch.rand(10, 36)
        w = bilateral_weights(ref, patch_offsets(5, 2), 5.0, 0.2)
        assert torch.allclose(bilateral_ncc(ref, ref, w), torch.zeros(10), atol=1e-5)

    def test_gain_offset_invariant(self):
        ref = torch.rand(10, 36)
        w = torch.full_like(ref, 1 / 36)
        assert torch.allclose(bilateral_ncc(ref, 0.5 * ref + 0.2, w), torch.zeros(10), atol=1e-5)

    def test_range_and_flat(self):
        ref = torch.rand(10, 36)
        w = torch.full_like(ref, 1 / 36)
        c = bilateral_ncc(ref, torch.rand(10, 36), w)
        assert ((c >= 0) & (c <= 2)).all()
        assert (bilateral_ncc(ref, torch.full_like(ref, 0.3), w) == MAX_COST).all()
        assert (bilateral_ncc(torch.full_like(ref, 0.3), ref, w) == MAX_COST).all()

    def test_against_loop(self):
        g = torch.Generator().manual_seed(0)
        ref = torch.rand(20, 36, generator=g)
        src = 0.6 * ref + 0.4 * torch.rand(20, 36, generator=g)
        src[3] = 0.5  # flat source
        w = bilateral_weights(ref, patch_offsets(5, 2), 5.0, 0.2)
        want = _ncc_naive(ref, src, w)
        assert torch.allclose(bilateral_ncc(ref, src, w).double(), want, atol=1e-5)
        # the sample-major fast path of PatchMatch equals both
        st = reference_patch_stats(ref.T[None], w.T[None].contiguous())
        fast = ncc_cost_from_stats(src.T[None, None].contiguous(), st)
        assert fast.shape == (1, 1, 20)
        assert torch.allclose(fast[0, 0].double(), want, atol=1e-4)

    def test_fast_path_multi_view(self):
        ref = torch.rand(2, 36, 7)
        w = torch.softmax(torch.rand(2, 36, 7), dim=1)
        st = reference_patch_stats(ref, w)
        src = torch.rand(2, 3, 36, 7)
        src[:, 1] = ref * 2 + 0.1
        got = ncc_cost_from_stats(src, st)
        assert got.shape == (2, 3, 7)
        assert torch.allclose(got[:, 1], torch.zeros(2, 7), atol=1e-4)
        want = bilateral_ncc(ref.transpose(1, 2)[:, None], src.transpose(2, 3), w.transpose(1, 2)[:, None])
        assert torch.allclose(got, want, atol=1e-4)
