"""What the loop's ``info`` must contain for each base strategy (:mod:`vadgs.train.vad.info`), checked
at VAD-GS's first step (docs/vad.md, "What `info` must contain"), and the values of the keys VAD-GS
reads itself: each wrong one raises a :class:`ValueError` naming the key, the expected and the actual."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from vadgs.train.strategy import DefaultStrategy
from vadgs.train.vad import StrategyContext, VisibilityAwareDensification, check_info, info_requirements

try:
    import gsplat.strategy as gsplat_strategy
except ImportError:  # the tests with gsplat's strategies as the base skip
    gsplat_strategy = None
needs_gsplat = pytest.mark.skipif(gsplat_strategy is None, reason="needs gsplat")


def _gsplat_meta(packed: bool = False) -> dict:
    means2d = torch.zeros(1, 5, 2, requires_grad=True) * 1.0  # a non-leaf, as the rasterizer's
    return {"means2d": means2d, "width": 8, "height": 6, "n_cameras": 1, "radii": torch.ones(1, 5, 2),
            "gaussian_ids": torch.arange(5) if packed else None}  # fmt: skip


def _first_step(base, info, **kwargs) -> None:
    """The first step's calls up to the base's: pre-backward, then post-backward with ``kwargs``
    (no event in reach: a sampling cycle of 100 steps; no view in ``info``: nothing is tested)."""
    vad = VisibilityAwareDensification(base=base)
    vad.context = StrategyContext(lambda v: None, total_steps=10, steps_per_cycle=100)
    vad.step_pre_backward({}, {}, {}, 0, info)
    base.step_post_backward = lambda *a, **k: None  # what is tested is the check before it
    vad.step_post_backward({}, {}, {"vad_cycle": 0}, 0, info, **kwargs)


@needs_gsplat
def test_gsplat_default_strategy_names_the_missing_key():
    info = _gsplat_meta()
    _first_step(gsplat_strategy.DefaultStrategy(), info)  # gsplat's meta: fine
    del info["gaussian_ids"]  # a hand-written loop's info (the AssertionError in gsplat)
    msg = r"info: expected key 'gaussian_ids' \(read by gsplat's DefaultStrategy; from the meta dict gsplat"
    with pytest.raises(ValueError, match=msg):
        _first_step(gsplat_strategy.DefaultStrategy(), info)
    with pytest.raises(
        ValueError, match=r"info\['gaussian_ids'\]: expected the ids of .*packed=True, got None"
    ):
        _first_step(gsplat_strategy.DefaultStrategy(), _gsplat_meta(), packed=True)
    _first_step(gsplat_strategy.DefaultStrategy(), _gsplat_meta(packed=True), packed=True)
    custom = gsplat_strategy.DefaultStrategy(key_for_gradient="gradient_2dgs")
    with pytest.raises(ValueError, match="expected key 'gradient_2dgs'"):
        _first_step(custom, _gsplat_meta())


@needs_gsplat
def test_vadgs_default_and_gsplat_mcmc():
    with pytest.raises(ValueError, match=r"expected key 'width' \(read by vadgs's DefaultStrategy"):
        _first_step(DefaultStrategy(), {"means2d": torch.zeros(1, 5, 2)})
    with pytest.raises(
        ValueError, match=r"expected key 'image_size' \(read by vadgs's DefaultStrategy; from the"
    ):
        check_info(DefaultStrategy(), {"raster": object()})
    check_info(DefaultStrategy(), {k: v for k, v in _gsplat_meta().items() if k != "gaussian_ids"})
    unpacked = {k: v for k, v in _gsplat_meta().items() if k != "gaussian_ids"}
    with pytest.raises(ValueError, match=r"expected key 'gaussian_ids' \(read by vadgs's DefaultStrategy"):
        check_info(DefaultStrategy(), unpacked, packed=True)
    check_info(DefaultStrategy(), _gsplat_meta(packed=True), packed=True)
    _first_step(gsplat_strategy.MCMCStrategy(), {})  # MCMC reads nothing from info (it takes lr=)
    check_info(object(), {})  # an unknown base: nothing is known, nothing checked


@needs_gsplat
def test_the_declaration_decides_not_the_module_name():
    class Mine:  # a user's strategy: declares what it reads
        def info_keys(self, packed=False):
            return [{"my_key": "my loop's render"}]

    with pytest.raises(ValueError, match=r"expected key 'my_key' \(read by .*Mine; from my loop's render\)"):
        check_info(Mine(), {"other": 1})
    check_info(Mine(), {"my_key": 1})

    class Tuned(gsplat_strategy.DefaultStrategy):  # a subclass of gsplat's: its base's entry
        pass

    with pytest.raises(ValueError, match=r"expected key 'gaussian_ids' \(read by .*Tuned"):
        check_info(Tuned(), {k: v for k, v in _gsplat_meta().items() if k != "gaussian_ids"})
    lookalike = type("Lookalike", (), {"__module__": "gsplat.strategy.custom", "key_for_gradient": "means2d"})
    assert info_requirements(lookalike()) == []  # a gsplat module name alone declares nothing
    assert [sorted(a) for a in info_requirements(DefaultStrategy(), packed=True)] == [
        ["image_size", "raster"],
        ["gaussian_ids", "height", "means2d", "radii", "width"],
    ]


class _NoBase:
    """A base strategy that reads nothing (as gsplat's MCMCStrategy): only the VAD-GS checks run."""

    def initialize_state(self, scene_scale: float = 1.0) -> dict:
        return {}

    def step_pre_backward(self, *args, **kwargs) -> None:
        pass

    def step_post_backward(self, *args, **kwargs) -> None:
        pass


@pytest.fixture
def strategy(tiny_index):
    """A strategy with inputs, index and context (no event in reach), and its state."""
    s = VisibilityAwareDensification(base=_NoBase())
    ctx = StrategyContext(render=lambda v: None, total_steps=100, steps_per_cycle=10)
    s.prepare(context=ctx, index=tiny_index)
    return s, s.initialize_state(1.0)


def _post(strategy, info):
    s, state = strategy
    s.step_post_backward({}, {}, state, 0, info)


class TestInfo:
    def test_valid_info_passes(self, strategy, tiny_inputs):
        v = tiny_inputs.train_views[0]
        h, w = tiny_inputs.size(v)
        _post(
            strategy,
            {"view": v, "image_size": (h, w), "depth": torch.ones(1, h, w), "alpha": torch.ones(h, w)},
        )
        _post(strategy, {"view": np.int64(v), "height": h, "width": w, "depth": torch.ones(1, 1, h, w)})
        _post(strategy, {})

    @pytest.mark.parametrize("view", [-1, 10**6, 2.5, "0"])
    def test_view(self, strategy, view):
        with pytest.raises(ValueError, match=r"^info\['view'\]: expected an integer in \[0, \d+\]"):
            _post(strategy, {"view": view})

    @pytest.mark.parametrize(
        ("info", "key"),
        [
            ({"image_size": (0, 10)}, r"info\['image_size'\]: expected positive \(H, W\), got \(0, 10\)"),
            ({"image_size": "big"}, r"info\['image_size'\]: expected \(H, W\), got 'big'"),
            ({"width": 0, "height": 10}, r"info\['width'\]: expected an integer >= 1, got 0"),
            ({"width": 10, "height": -3}, r"info\['height'\]: expected an integer >= 1, got -3"),
            ({"width": 10.5, "height": 10}, r"info\['width'\]: expected an integer >= 1, got 10\.5"),
        ],
    )
    def test_sizes(self, strategy, info, key):
        with pytest.raises(ValueError, match=f"^{key}"):
            _post(strategy, info)

    def test_depth_and_alpha_shapes(self, strategy, tiny_inputs):
        v = tiny_inputs.train_views[0]
        h, w = tiny_inputs.size(v)
        with pytest.raises(
            ValueError,
            match=rf"^info\['depth'\]: expected the view's depth of shape .*, got \(1, {h}, {w + 1}\)",
        ):
            _post(strategy, {"view": v, "image_size": (h, w), "depth": torch.ones(1, h, w + 1)})
        with pytest.raises(
            ValueError, match=r"^info\['alpha'\]: expected the view's alpha of shape .*, got \(1, 5, 6, 1\)"
        ):
            _post(strategy, {"view": v, "alpha": torch.ones(1, 5, 6, 1)})  # channel-last
        with pytest.raises(ValueError, match=r"^info\['depth'\]: expected a torch\.Tensor"):
            _post(strategy, {"view": v, "depth": np.ones((h, w))})
        with pytest.raises(ValueError, match=r"^info\['depth'\], info\['alpha'\]: expected maps of one size"):
            _post(strategy, {"view": v, "depth": torch.ones(h, w), "alpha": torch.ones(h - 1, w)})

    def test_raster_depth_is_named(self, strategy):
        raster = type("Raster", (), {"depth": torch.ones(1, 2, 5, 6), "alpha": None})()
        with pytest.raises(ValueError, match=r"^info\['raster'\]\.depth: expected the view's depth"):
            _post(strategy, {"raster": raster})
