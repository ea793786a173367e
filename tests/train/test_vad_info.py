"""What the loop's ``info`` must contain for each base strategy, checked at VAD-GS's first step
(docs/vad.md, "What `info` must contain")."""

from __future__ import annotations

import pytest
import torch

from vadgs.train.strategy import DefaultStrategy
from vadgs.train.vad import StrategyContext, VisibilityAwareDensification, check_info, info_requirements

gsplat_strategy = pytest.importorskip("gsplat.strategy")


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
