"""The hard depth composited in the render's own pass (``rasterize_gaussians(hard_depth=True)``)
against the two-render result (a second render with every opacity 1): values and gradients in
float64, the densification statistic, and the trainer's fused step."""

from __future__ import annotations

import pytest
import torch

from vadgs.render import RasterConfig, rasterize_gaussians

from .naive import random_scene

NAMES = ("color", "alpha", "depth", "normals")


def _fused_and_two_renders(n, size, seed, batch=1, cfg=None, **scene_kw):
    """Outputs and gradients of the fused render and of the two renders, same random loss."""
    sc = random_scene(n, size, seed=seed, dtype=torch.float64, batch=batch, **scene_kw)
    cfg = cfg or RasterConfig(chunk_size=4)
    g = torch.Generator().manual_seed(seed + 1)
    weights = {k: None for k in (*NAMES, "hard")}

    def loss_of(out, hard):
        for k in weights:
            if weights[k] is None:
                shape = (hard if k == "hard" else getattr(out, k)).shape
                weights[k] = torch.randn(shape, generator=g, dtype=torch.float64)
        return sum((getattr(out, k) * weights[k]).sum() for k in NAMES) + (hard * weights["hard"]).sum()

    params = [t.clone().requires_grad_(True) for t in sc[:5]]
    fused = rasterize_gaussians(*params, sc[5], sc[6], size, config=cfg, hard_depth=True)
    fused_loss = loss_of(fused, fused.hard_depth)
    fused_grads = torch.autograd.grad(fused_loss, [*params, fused.means2d], retain_graph=True)

    ref = [t.clone().requires_grad_(True) for t in sc[:5]]
    soft = rasterize_gaussians(*ref, sc[5], sc[6], size, config=cfg)
    ones = torch.ones_like(ref[3]).detach()
    hard = rasterize_gaussians(ref[0], ref[1], ref[2], ones, ref[4], sc[5], sc[6], size, config=cfg)
    ref_loss = loss_of(soft, hard.depth)
    ref_grads = torch.autograd.grad(ref_loss, [*ref, soft.means2d])
    return fused, (soft, hard), fused_grads, ref_grads


class TestHardDepthInTheSamePass:
    @pytest.mark.parametrize(
        "seed, batch, scene_kw",
        [
            (0, 1, {"opac": (0.05, 0.6)}),  # transparent Gaussians: at opacity 1 they reach further
            (1, 2, {"opac": (0.2, 0.95), "scale": (0.05, 0.4)}),  # two cameras
            (2, 1, {"opac": (0.002, 0.01)}),  # below alpha_min at their own opacity: only the hard pass
        ],
    )
    def test_values_and_gradients_equal_two_renders(self, seed, batch, scene_kw):
        fused, (soft, hard), fg, rg = _fused_and_two_renders(80, (20, 28), seed, batch, **scene_kw)
        for k in NAMES:
            torch.testing.assert_close(getattr(fused, k), getattr(soft, k), atol=1e-10, rtol=0, msg=k)
        torch.testing.assert_close(fused.hard_depth, hard.depth, atol=1e-9, rtol=0)
        assert float((hard.alpha > 0.5).float().mean()) > 0.2  # the hard pass has something to show
        assert not torch.equal(hard.depth, soft.depth)  # and it is not the soft depth
        names = ("means", "quats", "scales", "opacities", "colors", "means2d")
        for name, a, b in zip(names, fg, rg):
            torch.testing.assert_close(a, b, atol=1e-9 * float(b.abs().max()), rtol=0, msg=name)
        assert float(fg[0].abs().max()) > 0

    def test_means2d_grad_is_the_colour_pass_only(self):
        """The densification statistic (means2d.grad) does not see the hard depth's gradient."""
        sc = random_scene(40, (16, 16), seed=4, dtype=torch.float64)
        params = [t.clone().requires_grad_(True) for t in sc[:5]]
        out = rasterize_gaussians(*params, sc[5], sc[6], (16, 16), hard_depth=True)
        out.hard_depth.sum().backward()
        assert out.means2d.grad is not None and float(out.means2d.grad.abs().max()) == 0.0
        assert float(params[0].grad.abs().max()) > 0  # while the means do get it

    def test_absgrad_is_the_colour_pass_only(self):
        sc = random_scene(40, (16, 16), seed=5, dtype=torch.float64)
        cfg = RasterConfig(absgrad=True)
        params = [t.clone().requires_grad_(True) for t in sc[:5]]
        fused = rasterize_gaussians(*params, sc[5], sc[6], (16, 16), config=cfg, hard_depth=True)
        (fused.color.sum() + fused.hard_depth.sum()).backward()
        plain = rasterize_gaussians(*[t.clone().requires_grad_(True) for t in sc[:5]], sc[5], sc[6], (16, 16),
                                    config=cfg)  # fmt: skip
        plain.color.sum().backward()
        torch.testing.assert_close(fused.means2d_absgrad, plain.means2d_absgrad, atol=1e-10, rtol=0)

    def test_errors(self):
        sc = random_scene(5, (8, 8), seed=0)
        with pytest.raises(ValueError, match="hard_depth: expected RasterConfig\\(antialiased=False\\)"):
            rasterize_gaussians(*sc, (8, 8), config=RasterConfig(antialiased=True), hard_depth=True)
        plain = rasterize_gaussians(*sc, (8, 8))
        assert plain.hard_depth is None


def _count_calls(obj, name: str) -> list:
    """Replace ``obj.name`` by a wrapper that records its first argument in the returned list."""
    calls, inner = [], getattr(obj, name)
    setattr(obj, name, lambda v, *a, **k: calls.append(v) or inner(v, *a, **k))
    return calls


class TestTrainerFusedHardDepth:
    def test_fused_step_equals_the_two_render_step(self):
        """One step with the hard loss: the fused pass gives the two-render step's gradients."""
        from vadgs.data import load_scene, sample_scene_path
        from vadgs.train.config import TrainConfig
        from vadgs.train.losses import GeometricLossConfig
        from vadgs.train.trainer import Trainer
        from vadgs.train.vad import VisibilityDensifyConfig

        scene = load_scene(sample_scene_path(), scale=0.5)
        results = []
        for fused in (False, True):
            cfg = TrainConfig(
                iterations=10, checkpoint_every=10**6,
                geometry=GeometricLossConfig(hard_every=1, hard_stride=1, hard_fused=fused),
                vad=VisibilityDensifyConfig(every_cycles=10**6),
            )  # fmt: skip
            trainer = Trainer(scene, cfg, progress=False)
            calls = _count_calls(trainer.model, "render_depth")  # a second render
            # keep the step's gradients: no optimizer update, no zeroing
            trainer.optimizer.step = trainer.optimizer.zero_grad = lambda *a, **k: None
            res = trainer.train_step()
            results.append((trainer, res, calls))
        (two, res2, calls2), (one, res1, calls1) = results
        assert "hard" in res2 and res2["hard"] > 0 and len(calls2) == 1 and calls1 == []
        assert res1["hard"] == pytest.approx(res2["hard"], rel=1e-5)
        for k in ("means", "log_scales", "sh_dc", "opacity_logits", "quats"):
            g1, g2 = one.model.params[k].grad, two.model.params[k].grad
            # float32 rounding; the quats' gradients are ~1e-11 (isotropic initial Gaussians)
            atol = max(1e-4 * float(g2.abs().max()), 1e-9)
            torch.testing.assert_close(g1, g2, atol=atol, rtol=0, msg=k)
        assert float(two.model.params["means"].grad.abs().max()) > 1e-4

    def test_config_errors(self):
        from vadgs.train.config import TrainConfig
        from vadgs.train.losses import GeometricLossConfig

        with pytest.raises(ValueError, match=r"^geometry\.hard_fused: expected geometry\.hard_stride 1"):
            TrainConfig(geometry=GeometricLossConfig(hard_fused=True))  # hard_stride 2 by default
        fused = GeometricLossConfig(hard_fused=True, hard_stride=1)
        with pytest.raises(ValueError, match="backend 'gsplat'"):
            TrainConfig(geometry=fused, raster=RasterConfig(backend="gsplat"))
        with pytest.raises(ValueError, match="antialiased True"):
            TrainConfig(geometry=fused, raster=RasterConfig(antialiased=True))
        assert TrainConfig(geometry=fused).geometry.hard_fused
