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

    def test_hard_switched_off_after_80_percent(self):
        w = [L.geometric_weights(s, 100)["hard"] for s in range(100)]
        assert w[:80] == [0.1] * 80 and w[80:] == [0.0] * 20
