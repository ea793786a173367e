from __future__ import annotations

import pytest
import torch

from vadgs.render import RenderOutput
from vadgs.train.model import PER_GAUSSIAN, GaussianModel, make_optimizer
from vadgs.train.strategy import DefaultStrategy, DefaultStrategyConfig, Strategy


def _fake_info(n, grad_rows, h=10, w=20):
    means2d = torch.zeros(1, n, 2, requires_grad=True)
    means2d.grad = torch.zeros(1, n, 2)
    means2d.grad[0, grad_rows, 0] = 1.0  # pixel gradient 1 -> NDC 10
    z = torch.zeros(1, 1, h, w)
    raster = RenderOutput(
        z.expand(1, 3, h, w),
        z,
        z,
        z,
        z.expand(1, 3, h, w),
        torch.zeros(1, h, w, dtype=torch.long),
        means2d,
        None,
        torch.ones(1, n, 2, dtype=torch.int32),
        torch.ones(1, n, dtype=torch.bool),
        torch.ones(1, n),
    )
    return {
        "raster": raster,
        "ids": torch.arange(n),
        "image_size": (h, w),
        "generator": torch.Generator().manual_seed(0),
    }


def _model(n=6):
    log_scales = torch.full((n, 3), -5.0)
    log_scales[1] = 0.0  # big: split
    m = GaussianModel(
        torch.randn(n, 3),
        torch.rand(n, 3),
        log_scales,
        torch.full((n,), -1),
        torch.zeros(0, 1, 4, 4),
        torch.zeros(0, 1, dtype=torch.bool),
        [],
        sh_degree=0,
        init_opacity=0.5,
    )
    m.params["opacity_logits"].data[5] = -10.0  # transparent: pruned
    return m


class TestDefaultStrategy:
    def test_protocol(self):
        assert isinstance(DefaultStrategy(), Strategy)

    def test_clone_split_prune(self):
        m = _model()
        opt = make_optimizer(m, dict.fromkeys([*PER_GAUSSIAN, "sky"], 1e-3))
        s = DefaultStrategy(
            DefaultStrategyConfig(refine_start_iter=0, refine_every=2, grow_scale3d=0.1, reset_every=0)
        )
        state = s.initialize_state(scene_scale=1.0)
        s.step_post_backward(m.params, opt, state, 1, _fake_info(6, [0, 1]))
        assert state["count"].tolist() == [1.0] * 6 and state["grad2d"][0] == 10.0
        s.step_post_backward(m.params, opt, state, 2, _fake_info(6, [0, 1]))
        # 0 cloned (+1), 1 split (+1), 5 pruned (-1)
        assert state["last_refine"] == {"cloned": 1, "split": 1, "pruned": 1, "total": 7}
        assert m.num_gaussians == 7 and state["grad2d"].shape == (7,) and float(state["grad2d"].sum()) == 0.0
        for g in opt.param_groups[:-1]:
            assert g["params"][0] is m.params[g["name"]]
        sum(p.sum() for p in m.params.values()).backward()
        opt.step()

    def test_cap(self):
        m = _model()
        opt = make_optimizer(m, dict.fromkeys([*PER_GAUSSIAN, "sky"], 1e-3))
        s = DefaultStrategy(
            DefaultStrategyConfig(refine_start_iter=0, refine_every=1, max_gaussians=7, prune_opa=0.0)
        )
        state = s.initialize_state(1.0)
        s.step_post_backward(m.params, opt, state, 1, _fake_info(6, [0, 2, 3, 4]))
        assert m.num_gaussians == 7

    def test_reset(self):
        m = _model()
        opt = make_optimizer(m, dict.fromkeys([*PER_GAUSSIAN, "sky"], 1e-3))
        s = DefaultStrategy(DefaultStrategyConfig(refine_start_iter=100, reset_every=3))
        state = s.initialize_state(1.0)
        s.step_post_backward(m.params, opt, state, 3, _fake_info(6, []))
        assert (
            state["num_resets"] == 1
            and float(torch.sigmoid(m.params["opacity_logits"].detach()).max()) <= 0.0101
        )

    def test_check_sanity(self):
        m = _model()
        opt = make_optimizer(m, dict.fromkeys([*PER_GAUSSIAN, "sky"], 1e-3))
        DefaultStrategy().check_sanity(m.params, opt)
        splats = {k: torch.zeros(4, 3, requires_grad=True) for k in ("means", "quats", "scales", "opacities")}
        opts = {k: torch.optim.Adam([v]) for k, v in splats.items()}
        DefaultStrategy().check_sanity(splats, opts)  # gsplat's layout and optimizers
        del opts["quats"]
        with pytest.raises(ValueError, match=r"^optimizers: expected a key 'quats', got keys \["):
            DefaultStrategy().check_sanity(splats, opts)

    def test_gsplat_keyword_arguments(self):
        """gsplat's loops pass ``packed=`` (DefaultStrategy) or ``lr=`` (MCMCStrategy): accepted;
        ``packed`` means nothing for vadgs's own render, the others are ignored."""
        stats = []
        for kwargs in ({}, {"packed": False}, {"packed": True}, {"lr": 1e-3, "extra": None}):
            m = _model()
            opt = make_optimizer(m, dict.fromkeys([*PER_GAUSSIAN, "sky"], 1e-3))
            s = DefaultStrategy(DefaultStrategyConfig(refine_start_iter=10))
            state = s.initialize_state(1.0)
            info = _fake_info(6, [0, 1])
            s.step_pre_backward(m.params, opt, state, 1, info, **kwargs)
            s.step_post_backward(m.params, opt, state, 1, info, **kwargs)
            stats.append((state["grad2d"].tolist(), state["count"].tolist()))
        assert stats == [stats[0]] * 4 and stats[0][0][0] == 10.0


class TestInitializeBaseState:
    """``initialize_base_state``: a wrapped strategy's state, with ``scene_scale`` only when it takes one."""

    class _NoScale:  # gsplat's MCMCStrategy's signature
        def initialize_state(self):
            return {"calls": "no-arg"}

    class _Scale:
        def initialize_state(self, scene_scale=1.0):
            return {"scale": scene_scale}

    def test_with_and_without_scene_scale(self):
        from vadgs.train.strategy import initialize_base_state

        assert initialize_base_state(self._NoScale(), 3.0) == {"calls": "no-arg"}
        assert initialize_base_state(self._Scale(), 3.0) == {"scale": 3.0}
        assert initialize_base_state(DefaultStrategy(), 2.5)["scene_scale"] == 2.5

    def test_the_vad_strategy_wraps_a_base_without_scene_scale(self):
        from vadgs.train.vad import VisibilityAwareDensification

        state = VisibilityAwareDensification(base=self._NoScale()).initialize_state(4.0)
        assert state["calls"] == "no-arg" and state["vad_events"] == [] and state["vad_cycle"] == 0
        with pytest.raises(ValueError, match="scene_scale: expected a finite number > 0, got -1"):
            VisibilityAwareDensification(base=self._Scale()).initialize_state(-1)
