from __future__ import annotations

import pytest
import torch

from vadgs.train import losses as L


class TestColorLoss:
    def test_zero_and_positive(self):
        x = torch.rand(1, 3, 20, 20)
        assert L.color_loss(x, x).item() == pytest.approx(0.0, abs=1e-6)
        assert L.color_loss(x, 1 - x).item() > 0.1

    def test_l1_part(self):
        x = torch.zeros(1, 3, 20, 20)
        assert L.color_loss(x + 0.1, x, ssim_weight=0.0).item() == pytest.approx(0.1)

    def test_mask(self):
        x, y = torch.zeros(1, 3, 8, 8), torch.zeros(1, 3, 8, 8)
        y[..., :4] = 1.0
        mask = torch.zeros(1, 1, 8, 8, dtype=torch.bool)
        mask[..., 4:] = True
        assert L.color_loss(x, y, 0.0, mask).item() == 0.0

    def test_bad_shape(self):
        with pytest.raises(ValueError, match="pred"):
            L.color_loss(torch.zeros(3, 8, 8), torch.zeros(3, 8, 8))

    def test_gradcheck(self):
        x = torch.rand(1, 3, 6, 6, dtype=torch.float64, requires_grad=True)
        y = torch.rand(1, 3, 6, 6, dtype=torch.float64)
        assert torch.autograd.gradcheck(lambda a: L.color_loss(a, y), (x,), fast_mode=True)

    @pytest.mark.parametrize("shape", [(1, 3, 144, 240), (2, 3, 17, 23)])
    def test_ssim_map_is_kornias_with_fewer_launches(self, shape):
        """The moments filtered together: kornia's map (bit for bit here) and gradient (to rounding)."""
        from kornia.metrics import ssim

        from ..launch_count import LaunchCounter

        g = torch.Generator().manual_seed(0)
        a = torch.rand(*shape, generator=g, requires_grad=True)
        b = torch.rand(*shape, generator=g)
        ref = ssim(a, b, 11)
        with LaunchCounter() as ours_count:
            ours = L.ssim_map(a, b, 11)
        with LaunchCounter() as ref_count:
            ssim(a, b, 11)
        assert (ours - ref).abs().max() <= 1e-6
        (g_ref,) = torch.autograd.grad(ref.mean(), a)
        (g_ours,) = torch.autograd.grad(ours.mean(), a)
        assert (g_ours - g_ref).abs().max() <= 1e-5 * g_ref.abs().max()
        assert ours_count.launches * 2 <= ref_count.launches, (ours_count.launches, ref_count.launches)


class TestDepthAndNormal:
    def test_depth_reference(self):
        pred = torch.rand(2, 1, 5, 6) * 10
        tgt = torch.rand(2, 1, 5, 6) * 10
        tgt[0, 0, :2] = 0
        naive = [abs(p - t) / t for p, t in zip(pred.flatten().tolist(), tgt.flatten().tolist()) if t > 0]
        assert L.depth_loss(pred, tgt).item() == pytest.approx(sum(naive) / len(naive), rel=1e-5)
        assert L.depth_loss_soft(pred, tgt).item() == L.depth_loss_hard(pred, tgt).item()

    def test_depth_no_target_is_zero(self):
        assert L.depth_loss(torch.ones(1, 1, 2, 2), torch.zeros(1, 1, 2, 2)).item() == 0.0

    def test_normal(self):
        n = torch.nn.functional.normalize(torch.randn(1, 3, 4, 4), dim=1)
        assert L.normal_loss(n, n).item() == pytest.approx(0.0, abs=1e-6)
        assert L.normal_loss(n, -n).item() == pytest.approx(2.0, abs=1e-6)

    def test_gradcheck(self):
        p = (torch.rand(1, 1, 4, 4, dtype=torch.float64) + 1).requires_grad_()
        t = torch.rand(1, 1, 4, 4, dtype=torch.float64) + 1.5
        assert torch.autograd.gradcheck(lambda a: L.depth_loss(a, t), (p,))
        n = torch.randn(1, 3, 3, 3, dtype=torch.float64, requires_grad=True)
        tn = torch.randn(1, 3, 3, 3, dtype=torch.float64)
        assert torch.autograd.gradcheck(lambda a: L.normal_loss(a, tn), (n,))

    def test_min_share(self):
        """Fewer pixels with a target than ``min_share`` of the image: their sum over that share."""
        pred = torch.rand(2, 1, 10, 10) * 10 + 1
        tgt = torch.zeros(2, 1, 10, 10)
        tgt[0, 0, :2, :3] = torch.rand(2, 3) * 10 + 1  # 6 of 200 pixels
        err = ((pred - tgt).abs() / tgt.clamp(min=1e-6))[tgt > 0]
        assert L.depth_loss(pred, tgt).item() == pytest.approx(err.mean().item(), rel=1e-6)
        assert L.depth_loss(pred, tgt, min_share=0.1).item() == pytest.approx(err.sum().item() / 20, rel=1e-6)
        assert L.depth_loss(pred, tgt, min_share=0.01).item() == pytest.approx(err.mean().item(), rel=1e-6)
        full = torch.rand(2, 1, 10, 10) + 1  # every pixel: the mean whatever the share
        mean = L.depth_loss(pred, full).item()
        assert L.depth_loss(pred, full, min_share=1.0).item() == pytest.approx(mean)
        n, tn = torch.randn(1, 3, 10, 10), torch.zeros(1, 3, 10, 10)
        tn[:, 2, :1, :5] = -1.0  # 5 of 100 pixels
        cos = torch.nn.functional.normalize(n, dim=1)[:, 2, :1, :5] * -1.0
        expected = (1 - cos).sum().item() / 50
        assert L.normal_loss(n, tn, min_share=0.5).item() == pytest.approx(expected, rel=1e-5)

    def test_geometric_losses_min_share(self):
        """One pixel with a prior: its gradient is the image share's, not the whole term's."""
        t = L.GeometryTargets(depth=torch.zeros(1, 1, 10, 10), normal=torch.zeros(1, 3, 10, 10))
        t.depth[0, 0, 4, 4] = 2.0
        t.normal[0, 2, 4, 4] = -1.0
        d = torch.full((1, 1, 10, 10), 3.0, requires_grad=True)
        n = torch.zeros(1, 3, 10, 10)
        n[:, 0] = 1.0
        w = L.geometric_weights(0, 10)
        mean = L.geometric_losses(t, d, n, w, min_share=0.0)
        share = L.geometric_losses(t, d, n, w)  # the config's default, 0.1: 10 pixels
        assert L.GeometricLossConfig().min_prior_share == 0.1
        assert mean["soft"].item() == pytest.approx(0.1 * 0.5)
        assert share["soft"].item() == pytest.approx(0.1 * 0.5 / 10)
        assert share["normal"].item() == pytest.approx(mean["normal"].item() / 10)
        (g,) = torch.autograd.grad(share["soft"], d)
        assert g[0, 0, 4, 4].item() == pytest.approx(0.1 / 2.0 / 10) and g.count_nonzero() == 1

    def test_hard_switched_off_after_80_percent(self):
        w = [L.geometric_weights(s, 100)["hard"] for s in range(100)]
        assert w[:80] == [0.1] * 80 and w[80:] == [0.0] * 20


class TestGeometricLossConfig:
    """The paper's geometric loss settings in one frozen, checked config (``TrainConfig.geometry``)."""

    def test_paper_defaults_and_weights(self):
        g = L.GeometricLossConfig()
        assert (g.lambda_normal, g.lambda_hard, g.lambda_soft, g.hard_until) == (0.02, 0.1, 0.1, 0.8)
        assert (g.hard_every, g.hard_stride, g.hard_fused) == (8, 2, False)
        for step in (0, 79, 80, 99):
            assert g.weights(step, 100) == L.geometric_weights(step, 100)
        assert g.weights(79, 100) == {"normal": 0.02, "hard": 0.1, "soft": 0.1}
        assert g.weights(80, 100) == {"normal": 0.02, "hard": 0.0, "soft": 0.1}

    def test_geometric_weights_is_the_config(self):
        """The function keeps its signature, with the config's defaults (written once)."""
        import inspect

        params = inspect.signature(L.geometric_weights).parameters
        for name in ("lambda_normal", "lambda_hard", "lambda_soft", "hard_until"):
            assert params[name].default == getattr(L.GeometricLossConfig(), name)
        g = L.GeometricLossConfig(lambda_normal=0.5, lambda_hard=0.3, lambda_soft=0.2, hard_until=0.5)
        for step in (0, 49, 50, 99):
            assert g.weights(step, 100) == L.geometric_weights(step, 100, 0.5, 0.3, 0.2, 0.5)
        with pytest.raises(ValueError, match="lambda_hard: expected a finite number >= 0, got -1"):
            L.geometric_weights(0, 100, lambda_hard=-1)

    def test_hard_applies(self):
        g = L.GeometricLossConfig(hard_every=4)
        applies = [s for s in range(100) if g.hard_applies(s, 100)]
        assert applies == list(range(0, 80, 4))  # every 4th step, until 80 % of the run
        assert not L.GeometricLossConfig(lambda_hard=0.0, hard_every=1).hard_applies(0, 100)
        assert not L.GeometricLossConfig(hard_until=0.0, hard_every=1).hard_applies(0, 100)
        every = L.GeometricLossConfig(hard_every=1)
        assert [s for s in range(10) if every.hard_applies(s, 10)] == list(range(8))

    @pytest.mark.parametrize(
        ("changes", "message"),
        [
            ({"lambda_normal": -0.1}, "lambda_normal: expected a finite number >= 0, got -0.1"),
            ({"lambda_hard": float("nan")}, "lambda_hard: expected a finite number >= 0, got nan"),
            ({"lambda_soft": float("inf")}, "lambda_soft: expected a finite number >= 0, got inf"),
            ({"lambda_soft": "0.1"}, "lambda_soft: expected a finite number >= 0, got str '0.1'"),
            ({"hard_until": 1.5}, r"hard_until: expected a finite number in \[0, 1\], got 1.5"),
            ({"hard_until": -0.1}, r"hard_until: expected a finite number in \[0, 1\], got -0.1"),
            ({"hard_every": 0}, "hard_every: expected an integer >= 1, got 0"),
            ({"hard_every": 2.5}, "hard_every: expected an integer >= 1, got 2.5"),
            ({"hard_stride": 0}, "hard_stride: expected an integer >= 1, got 0"),
            ({"hard_fused": 1}, "hard_fused: expected True or False, got 1"),
            ({"min_prior_share": 1.5}, r"min_prior_share: expected a finite number in \[0, 1\], got 1.5"),
        ],
    )
    def test_checks(self, changes, message):
        with pytest.raises(ValueError, match=f"^{message}$"):
            L.GeometricLossConfig(**changes)

    def test_frozen_and_normalised(self):
        import dataclasses

        g = L.GeometricLossConfig(lambda_hard=1, hard_until=1)
        assert type(g.lambda_hard) is float and type(g.hard_until) is float
        with pytest.raises(dataclasses.FrozenInstanceError):
            g.lambda_hard = 0.5  # type: ignore[misc]
