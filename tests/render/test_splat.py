from __future__ import annotations

import math

import pytest
import torch

from vadgs.geometry.camera import Cameras, camera_centers
from vadgs.render import GaussianRasterizer, RasterConfig, eval_sh, rasterize_gaussians

from .naive import random_scene, render_naive

NAMES = ("color", "alpha", "depth", "median_depth", "normals")
# Documented tolerances against the naive per-pixel reference: float64 agrees to ~1e-12,
# float32 outputs to 1e-4 absolute (depth 1e-3 m) and gradients to 1e-3 relative to their max.
TOL = {torch.float64: (1e-10, 1e-9), torch.float32: (1e-4, 1e-3)}


def _compare(n, size, seed, dtype, batch=1, cfg=None, sh=False, bg=True, **scene_kw):
    sc = random_scene(n, size, seed=seed, dtype=dtype, batch=batch, **scene_kw)
    colors = sc[4]
    if sh:
        colors = torch.randn(n, 9, 3, generator=torch.Generator().manual_seed(seed), dtype=dtype) * 0.3
    params = [t.clone().requires_grad_(True) for t in (*sc[:4], colors)]
    background = torch.tensor([0.1, 0.2, 0.3], dtype=dtype) if bg else None
    cfg = cfg or RasterConfig(chunk_size=4)
    out = rasterize_gaussians(*params, sc[5], sc[6], size, background=background, config=cfg)
    weights = [torch.randn_like(getattr(out, k)) for k in NAMES]
    loss = sum((getattr(out, k) * wt).sum() for k, wt in zip(NAMES, weights))
    grads = torch.autograd.grad(loss, params)
    ref_loss = 0
    atol, rtol = TOL[dtype]
    for b in range(batch):
        cols = params[4]
        if sh:
            dirs = torch.nn.functional.normalize(params[0] - camera_centers(sc[5][b : b + 1])[0], dim=-1)
            cols = eval_sh(params[4], dirs)
        ref = render_naive(
            *params[:4], cols, sc[5][b], sc[6][b], size, background=background,
            antialiased=cfg.antialiased, alpha_max=cfg.alpha_max,
        )  # fmt: skip
        for k, r, wt in zip(NAMES, ref, weights):
            tol = atol * (10 if k == "depth" else 1)
            torch.testing.assert_close(getattr(out, k)[b], r.detach(), atol=tol, rtol=0, msg=k)
            ref_loss = ref_loss + (r * wt[b]).sum()
    ref_grads = torch.autograd.grad(ref_loss, params)
    for name, g, r in zip(("means", "quats", "scales", "opacities", "colors"), grads, ref_grads):
        torch.testing.assert_close(g, r, atol=rtol * float(r.abs().max()), rtol=0, msg=name)
    return out


class TestRasterizeGaussians:
    def test_smoke(self, device, dtype):
        sc = random_scene(20, (16, 24), dtype=dtype)
        out = rasterize_gaussians(*sc, (16, 24))
        assert out.color.isfinite().all()
        assert 0 < out.alpha.max() <= 1

    @pytest.mark.parametrize("batch", [1, 3])
    def test_cardinality(self, batch, device, dtype):
        n, size = 15, (13, 21)
        sc = random_scene(n, size, batch=batch, dtype=dtype)
        out = rasterize_gaussians(*sc, size)
        h, w = size
        assert out.color.shape == (batch, 3, h, w)
        for k in ("alpha", "depth", "median_depth"):
            assert getattr(out, k).shape == (batch, 1, h, w)
        assert out.normals.shape == (batch, 3, h, w)
        assert out.median_ids.shape == (batch, h, w) and out.median_ids.dtype == torch.long
        assert out.means2d.shape == (batch, n, 2)
        assert out.radii.shape == (batch, n, 2) and out.radii.dtype == torch.int32
        assert out.visible.shape == (batch, n) and out.visible.dtype == torch.bool
        assert out.means2d_absgrad is None
        one = rasterize_gaussians(*sc[:4], sc[4][:, :1], *sc[5:], size)  # any number of channels
        assert one.color.shape == (batch, 1, h, w)
        sh = rasterize_gaussians(*sc[:4], torch.zeros(n, 16, 3), *sc[5:], size, sh_degree=2)
        assert sh.color.shape == (batch, 3, h, w)

    def test_exception(self, device, dtype):
        means, quats, scales, opac, cols, w2c, K = random_scene(5, (8, 8), dtype=dtype)
        size = (8, 8)
        with pytest.raises(ValueError, match="quats"):
            rasterize_gaussians(means, quats[:4], scales, opac, cols, w2c, K, size)
        with pytest.raises(ValueError, match="opacities"):
            rasterize_gaussians(means, quats, scales, opac[:, None], cols, w2c, K, size)
        with pytest.raises(ValueError, match="colors"):
            rasterize_gaussians(means, quats, scales, opac, cols[:3], w2c, K, size)
        with pytest.raises(ValueError, match="K"):
            rasterize_gaussians(means, quats, scales, opac, cols, w2c, K[0], size)
        with pytest.raises(ValueError, match="with B=2"):
            rasterize_gaussians(means, quats, scales, opac, cols, w2c.repeat(2, 1, 1), K, size)
        bad = quats.clone()
        bad[2] = 0
        with pytest.raises(ValueError, match="non-zero"):
            rasterize_gaussians(means, bad, scales, opac, cols, w2c, K, size)
        bad = means.clone()
        bad[1, 0] = float("nan")
        with pytest.raises(ValueError, match="means: expected finite"):
            rasterize_gaussians(bad, quats, scales, opac, cols, w2c, K, size)
        with pytest.raises(ValueError, match="log_scales"):
            rasterize_gaussians(means, quats, scales.log(), opac, cols, w2c, K, size)
        with pytest.raises(ValueError, match="sigmoid"):
            rasterize_gaussians(means, quats, scales, opac * 5 - 2, cols, w2c, K, size)
        with pytest.raises(ValueError, match="dtype"):
            rasterize_gaussians(means.double(), quats, scales, opac, cols, w2c, K, size)
        with pytest.raises(ValueError, match="background"):
            rasterize_gaussians(means, quats, scales, opac, cols, w2c, K, size, background=torch.zeros(4))
        with pytest.raises(ValueError, match="coeffs"):
            rasterize_gaussians(means, quats, scales, opac, torch.zeros(5, 5, 3), w2c, K, size)
        with pytest.raises(ValueError, match="degree"):
            rasterize_gaussians(means, quats, scales, opac, torch.zeros(5, 4, 3), w2c, K, size, sh_degree=2)
        with pytest.raises(ValueError, match="image_size"):
            rasterize_gaussians(means, quats, scales, opac, cols, w2c, K, (0, 8))
        with pytest.raises(ValueError, match="alpha_max"):
            RasterConfig(alpha_max=1.0)
        with pytest.raises(ValueError, match="near"):
            RasterConfig(near=0.0)

    def test_empty_scene_renders_background(self, device, dtype):
        _, _, _, _, _, w2c, K = random_scene(1, (8, 8), dtype=dtype, batch=2)
        z = torch.zeros(0, 3, dtype=dtype)
        bg = torch.tensor([0.2, 0.4, 0.6], dtype=dtype)
        out = rasterize_gaussians(z, torch.zeros(0, 4), z, torch.zeros(0), z, w2c, K, (8, 9), background=bg)
        assert torch.equal(out.color, bg[None, :, None, None].expand(2, 3, 8, 9))
        assert not out.alpha.any() and not out.depth.any() and not out.normals.any()
        assert (out.median_ids == -1).all() and out.radii.shape == (2, 0, 2)

    def test_all_behind_camera(self, device, dtype):
        means, quats, scales, opac, cols, w2c, K = random_scene(30, (8, 8), dtype=dtype)
        means = means.clone().requires_grad_(True)
        out = rasterize_gaussians(
            means - torch.tensor([0, 0, 10.0]), quats, scales, opac, cols, w2c, K, (8, 8)
        )
        assert not out.visible.any() and not out.alpha.any() and not out.color.any()
        out.color.sum().backward()
        assert torch.equal(means.grad, torch.zeros_like(means))

    def test_closed_form_isotropic(self, device):
        # One isotropic Gaussian on the optical axis: its screen covariance is (f s / z)^2 + eps2d
        # at every pixel, so alpha(u, v) = o exp(-|d|^2 / (2 var)), skipped below 1/255.
        f, s, z, o, size = 40.0, 0.1, 2.0, 0.8, (21, 25)
        f64 = torch.float64
        K = torch.tensor([[[f, 0, 12.0], [0, f, 10.0], [0, 0, 1]]], dtype=torch.float64)
        col = torch.tensor([[0.9, 0.5, 0.1]], dtype=torch.float64)
        bg = torch.tensor([0.0, 0.2, 1.0], dtype=torch.float64)
        out = rasterize_gaussians(
            torch.tensor([[0.0, 0.0, z]], dtype=f64), torch.tensor([[1.0, 0, 0, 0]], dtype=f64),
            torch.full((1, 3), s, dtype=f64), torch.tensor([o], dtype=f64), col,
            torch.eye(4, dtype=f64)[None], K, size, background=bg,
        )  # fmt: skip
        var = (f * s / z) ** 2 + 0.3
        v, u = torch.meshgrid(torch.arange(21.0, dtype=f64), torch.arange(25.0, dtype=f64), indexing="ij")
        alpha = o * torch.exp(-((u - 12) ** 2 + (v - 10) ** 2) / (2 * var))
        alpha = torch.where(alpha >= 1 / 255, alpha, torch.zeros_like(alpha))
        torch.testing.assert_close(out.alpha[0, 0], alpha, atol=1e-12, rtol=0)
        expect = alpha * col[0, :, None, None] + (1 - alpha) * bg[:, None, None]
        torch.testing.assert_close(out.color[0], expect, atol=1e-12, rtol=0)
        torch.testing.assert_close(
            out.depth[0, 0], torch.where(alpha > 0, z, 0.0).double(), atol=1e-12, rtol=0
        )
        assert out.median_depth[0, 0, 10, 12] == z and out.median_depth[0, 0, 0, 0] == 0
        # The shortest axis is ambiguous for a sphere; any unit axis facing the camera is right.
        assert out.normals[0, 2, 10, 12] <= 0 and torch.isclose(
            out.normals[0, :, 10, 12].norm(), torch.tensor(1.0).double()
        )
        assert out.radii[0, 0].tolist() == [math.ceil(math.sqrt(2 * math.log(o * 255)) * math.sqrt(var))] * 2

    @pytest.mark.parametrize("dtype_", [torch.float64, torch.float32])
    def test_feature_vs_naive(self, dtype_):
        _compare(12, (12, 14), seed=1, dtype=dtype_, batch=2)

    def test_feature_vs_naive_dense_stop_rule(self):
        # Opaque overlapping Gaussians: pixels hit T < 1e-4 and stop; tiles exit early.
        out = _compare(60, (12, 16), seed=6, dtype=torch.float64, opac=(0.97, 0.999), scale=(0.3, 0.8))
        assert (out.alpha > 0.999).float().mean() > 0.3 and (out.median_depth > 0).float().mean() > 0.9

    def test_feature_vs_naive_antialiased_sh(self):
        _compare(
            20,
            (13, 21),
            seed=4,
            dtype=torch.float64,
            cfg=RasterConfig(antialiased=True, chunk_size=8),
            sh=True,
        )

    def test_feature_vs_naive_overhang_and_big_tiles(self):
        # 13 x 21 is not a multiple of the tile; 16-px tiles hang over the border on both axes.
        _compare(
            25, (13, 21), seed=5, dtype=torch.float32, cfg=RasterConfig(tile_size=16, chunk_size=3), bg=False
        )

    @pytest.mark.parametrize("backward", ["manual", "autograd"])
    def test_feature_vs_naive_growing_chunks(self, backward, monkeypatch):
        """Tiles with lists of very different lengths: the chunk doubles as tiles finish (up to 16
        here from 2), and the images and gradients still match the naive per-pixel reference."""
        import vadgs.render.composite as composite

        sizes = []
        chunk_size = composite._chunk_size

        def spy(s, n, n0):
            sizes.append(chunk_size(s, n, n0))
            return sizes[-1]

        monkeypatch.setattr(composite, "_chunk_size", spy)
        cfg = RasterConfig(chunk_size=2, backward=backward)
        _compare(150, (16, 40), seed=9, dtype=torch.float64, cfg=cfg, opac=(0.02, 0.3), scale=(0.05, 0.4))
        assert sizes[0] == 2 and max(sizes) == 16  # 10 tiles in the first step, 1 in the last: 2 x 8

    def test_feature_alpha_cap(self):
        cfg = RasterConfig(alpha_max=0.99, chunk_size=4)
        _compare(20, (10, 12), seed=8, dtype=torch.float64, cfg=cfg, opac=(0.995, 1.0), scale=(0.2, 0.5))

    def test_autograd_backend_matches(self):
        sc = random_scene(
            40, (20, 24), seed=3, dtype=torch.float64, batch=2, opac=(0.5, 0.999), scale=(0.1, 0.5)
        )
        outs, grads = [], []
        for backward in ("manual", "autograd"):
            params = [t.clone().requires_grad_(True) for t in sc[:5]]
            out = rasterize_gaussians(
                *params, *sc[5:], (20, 24), config=RasterConfig(backward=backward, chunk_size=8)
            )
            loss = sum((getattr(out, k) * (i + 1)).sum() for i, k in enumerate(NAMES))
            outs.append(out)
            grads.append(torch.autograd.grad(loss, params))
        for k in NAMES:
            torch.testing.assert_close(getattr(outs[0], k), getattr(outs[1], k))
        for g0, g1 in zip(*grads):
            torch.testing.assert_close(g0, g1)

    def test_means2d_grad_and_absgrad(self, dtype):
        sc = random_scene(30, (16, 20), seed=2, dtype=dtype)
        means = sc[0].clone().requires_grad_(True)
        out = rasterize_gaussians(means, *sc[1:], (16, 20), config=RasterConfig(absgrad=True))
        (out.color * torch.randn_like(out.color)).sum().backward()
        g, ab = out.means2d.grad, out.means2d_absgrad
        assert g is not None and g.shape == (1, 30, 2) and ab.shape == (1, 30, 2)
        assert (ab >= g.abs() - 1e-5).all()  # triangle inequality over pixels
        assert (ab[out.visible] > 0).any() and not ab[~out.visible].any()

    def test_gradcheck(self):
        sc = random_scene(4, (6, 7), seed=11, dtype=torch.float64, opac=(0.5, 0.9), scale=(0.2, 0.4))
        params = [t.clone().requires_grad_(True) for t in sc[:5]]

        def fn(*p):
            out = rasterize_gaussians(
                *p, *sc[5:], (6, 7), background=torch.full((3,), 0.3, dtype=torch.float64)
            )
            return out.color, out.alpha, out.depth, out.normals

        assert torch.autograd.gradcheck(fn, params, eps=1e-6, atol=1e-5, fast_mode=True)

    def test_module(self, dtype):
        sc = random_scene(10, (12, 12), dtype=dtype, batch=2)
        cfg = RasterConfig(antialiased=True)
        cams = Cameras(sc[6], sc[5], (12, 12))
        a = GaussianRasterizer(cfg)(*sc[:5], cams)
        b = rasterize_gaussians(*sc, (12, 12), config=cfg)
        for k in NAMES:
            assert torch.equal(getattr(a, k), getattr(b, k))
        assert "antialiased=True" in repr(GaussianRasterizer(cfg))

    @pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
    def test_cuda_matches_cpu(self):
        sc = random_scene(50, (24, 32), seed=3, opac=(0.5, 0.99))
        cpu = rasterize_gaussians(*sc, (24, 32))
        gpu = rasterize_gaussians(*(t.cuda() for t in sc), (24, 32))
        for k in NAMES:
            torch.testing.assert_close(getattr(gpu, k).cpu(), getattr(cpu, k), atol=1e-4, rtol=0)


class TestRasterizeRejectsDegenerateInputs:
    """Reliability trial (issue 17): a NaN image for huge scales, a finite one for K = 0."""

    def _args(self, scale=0.1, K=None):
        K = torch.tensor([[[50.0, 0, 16.0], [0, 50.0, 12.0], [0, 0, 1]]]) if K is None else K
        means, quats = torch.tensor([[0.0, 0.0, 4.0]]), torch.tensor([[1.0, 0, 0, 0]])
        scales, opac, rgb = torch.full((1, 3), scale), torch.tensor([0.5]), torch.tensor([[1.0, 0.5, 0.0]])
        return means, quats, scales, opac, rgb, torch.eye(4)[None], K, (24, 32)

    @pytest.mark.parametrize(
        "K",
        [torch.zeros(1, 3, 3), torch.tensor([[[-50.0, 0, 16.0], [0, 50.0, 12.0], [0, 0, 1]]])],
        ids=["zero", "negative-fx"],
    )
    def test_singular_K(self, K):
        with pytest.raises(ValueError, match=r"K: expected positive focal lengths .* for camera b=0"):
            rasterize_gaussians(*self._args(K=K))

    def test_overflowing_scales(self):
        with pytest.raises(ValueError, match=r"scales: expected < .* overflows the torch.float32 covariance"):
            rasterize_gaussians(*self._args(scale=1e20))

    def test_large_but_finite_scales_render(self):
        out = rasterize_gaussians(*self._args(scale=1e6))
        assert torch.isfinite(out.color).all()
