"""The Python API validates like the CLI (issue 39, item 5).

Every field of :class:`VisibilityDensifyConfig`, :class:`ReconstructConfig` and
:class:`IncompleteConfig` has one rule, next to the field (:func:`vadgs.checks.checked`;
``tests/test_config_rules.py`` checks every config of the package), run at construction and,
on :class:`VisibilityAwareDensification`, when a setting is set later;
``initialize_state(scene_scale)``, the loop's ``info`` and ``geometry_targets`` before ``prepare``
raise a :class:`ValueError` naming the argument, the expected and the actual.
"""

from __future__ import annotations

import dataclasses
import math
import typing

import numpy as np
import pytest
import torch

from vadgs.train.strategy import DefaultStrategy
from vadgs.train.vad import (
    ReconstructConfig,
    StrategyContext,
    VisibilityAwareDensification,
    VisibilityDensifyConfig,
    VisibilityInputs,
)
from vadgs.train.vad.incomplete import IncompleteConfig

NAN, INF = float("nan"), float("inf")
CONFIGS = (VisibilityDensifyConfig, ReconstructConfig, IncompleteConfig)


def _bad_values(tp: typing.Any) -> list[typing.Any]:
    """Values wrong for a field annotated ``tp`` whatever its range (every range here is >= 0)."""
    args = [a for a in typing.get_args(tp) if a is not type(None)]
    optional = type(None) in typing.get_args(tp)
    if optional and len(args) == 1:
        tp = args[0]
    origin, inner = typing.get_origin(tp), typing.get_args(tp)
    none = [] if optional else [None]
    if tp is bool:
        return [1, "yes", None]
    if tp is int:
        return [2.5, 3.0, True, "3", -1, NAN, *none]
    if tp is float:
        return [NAN, INF, -INF, -1.0, "0.5", True, torch.tensor(0.5), *none]
    if tp is str:
        return ["bogus", 3, None]
    if origin is tuple and inner == (str, ...):
        return ["road", ("road", 3), 5, None]
    if origin is tuple and inner == (int, ...):
        return ["0", (0, 2.5), (True,), None]
    if origin is tuple and inner == (float, float):
        return [(0.5,), (0.5, 2.0, 3.0), "ab", (NAN, 2.0), (-1.0, 2.0), *none]
    if dataclasses.is_dataclass(tp):
        return [{}, "default", *none]
    raise AssertionError(f"no bad values for {tp}")


def _cases():
    for cls in CONFIGS:
        hints = typing.get_type_hints(cls)
        for f in dataclasses.fields(cls):
            for bad in _bad_values(hints[f.name]):
                yield pytest.param(cls, f.name, bad, id=f"{cls.__name__}.{f.name}={bad!r}")


def _strategy_cases():
    hints = typing.get_type_hints(VisibilityDensifyConfig)
    for f in dataclasses.fields(VisibilityDensifyConfig):
        for bad in _bad_values(hints[f.name]):
            yield pytest.param(f.name, bad, id=f"{f.name}={bad!r}")


class TestEveryField:
    @pytest.mark.parametrize(("cls", "name", "bad"), list(_cases()))
    def test_bad_value_at_construction(self, cls, name, bad):
        with pytest.raises(ValueError) as e:
            cls(**{name: bad})
        msg = str(e.value)
        assert msg.startswith(name) and "expected" in msg and "got" in msg, msg

    @pytest.mark.parametrize(("name", "bad"), list(_strategy_cases()))
    def test_bad_value_set_on_the_strategy_after_construction(self, name, bad):
        s = VisibilityAwareDensification()
        before = getattr(s, name)
        with pytest.raises(ValueError) as e:
            setattr(s, name, bad)
        assert str(e.value).startswith(name), str(e.value)
        assert getattr(s, name) == before and s.config == VisibilityDensifyConfig()  # unchanged

    @pytest.mark.parametrize(("name", "bad"), list(_strategy_cases()))
    def test_bad_value_given_to_the_strategy(self, name, bad):
        with pytest.raises(ValueError, match=f"^{name}"):
            VisibilityAwareDensification(**{name: bad})


class TestMessages:
    def test_string_for_a_sequence(self):
        with pytest.raises(
            ValueError,
            match=r"^skip_classes: expected a sequence of class names, got the string 'road' "
            r"\(write \('road',\)\)$",
        ):
            VisibilityDensifyConfig(skip_classes="road")

    def test_non_integer_nan_negative(self):
        with pytest.raises(ValueError, match=r"^every_cycles: expected an integer >= 1, got 2\.5$"):
            VisibilityDensifyConfig(every_cycles=2.5)
        with pytest.raises(ValueError, match=r"^new_opacity: expected a finite number in \(0, 1\), got nan$"):
            VisibilityDensifyConfig(new_opacity=NAN)
        with pytest.raises(ValueError, match=r"^min_pixels: expected an integer >= 0, got -1$"):
            IncompleteConfig(min_pixels=-1)
        with pytest.raises(ValueError, match=r"^depth_margin: expected a pair \(near <= 1 <= far\)"):
            ReconstructConfig(depth_margin=(2.0, 3.0))
        with pytest.raises(ValueError, match=r"^fallback_depth_range: expected None or a pair \(lo < hi\)"):
            ReconstructConfig(fallback_depth_range=(5.0, 1.0))
        with pytest.raises(ValueError, match=r"^max_downsample: expected one of \(1, 2, 4, 8\), got 3$"):
            ReconstructConfig(max_downsample=3)

    def test_strategy_field_set_later_no_zero_division(self):
        s = VisibilityAwareDensification()
        with pytest.raises(ValueError, match=r"^every_cycles: expected an integer >= 1, got 0$"):
            s.every_cycles = 0
        with pytest.raises(ValueError, match=r"^log_size: expected an integer >= 1, got 0$"):
            s.log_size = 0
        assert s.every_cycles == 5 and s.log_size >= 1


class TestValidValues:
    def test_edge_values_accepted_and_normalised(self):
        cfg = VisibilityDensifyConfig(
            every_cycles=np.int64(1),
            max_instances=0,
            work_budget=None,
            render_cache_mb=0,
            references=1,
            min_frame_gap=0,
            skip_classes=["road", "sky"],
            new_opacity=np.float32(0.25),
            last_event_fraction=1,
            view_selection=np.bool_(True),
        )
        assert type(cfg.every_cycles) is int and cfg.every_cycles == 1
        assert cfg.skip_classes == ("road", "sky")  # a list becomes a tuple
        assert type(cfg.new_opacity) is float and type(cfg.last_event_fraction) is float
        assert cfg.view_selection is True
        assert VisibilityDensifyConfig(skip_classes=()).skip_classes == ()
        assert VisibilityDensifyConfig(last_event_fraction=0.0).last_event_fraction == 0.0
        rec = ReconstructConfig(
            depth_margin=(1, 1), fallback_depth_range=[0.1, 100], max_downsample=np.int64(8), planar=None
        )
        assert rec.depth_margin == (1.0, 1.0) and rec.fallback_depth_range == (0.1, 100.0)
        assert rec.max_downsample == 8 and type(rec.max_downsample) is int
        inc = IncompleteConfig(alpha_threshold=0, low_alpha_fraction=1, ignore_ids=[0, np.int64(3)])
        assert inc.ignore_ids == (0, 3) and all(type(i) is int for i in inc.ignore_ids)

    def test_defaults_unchanged(self):
        for cls in CONFIGS:
            assert cls() == cls()
        assert VisibilityDensifyConfig().skip_classes == ("road",)

    def test_strategy_setting_set_later_is_in_its_config(self):
        s = VisibilityAwareDensification()
        s.every_cycles = np.int64(2)
        s.skip_classes = ["road", "car"]
        assert s.every_cycles == 2 and s.skip_classes == ("road", "car")
        assert s.config == VisibilityDensifyConfig(every_cycles=2, skip_classes=("road", "car"))
        s.config = VisibilityDensifyConfig(references=1)
        assert s.every_cycles == 5 and s.config.references == 1


class TestContextAndScale:
    def test_strategy_context(self):
        with pytest.raises(ValueError, match=r"^steps_per_cycle: expected an integer >= 1, got 0$"):
            StrategyContext(render=lambda v: None, total_steps=10, steps_per_cycle=0)
        with pytest.raises(ValueError, match=r"^total_steps: expected an integer >= 0, got 2\.5$"):
            StrategyContext(render=lambda v: None, total_steps=2.5, steps_per_cycle=1)
        with pytest.raises(ValueError, match=r"^render: expected a function"):
            StrategyContext(render=None, total_steps=10, steps_per_cycle=1)

    @pytest.mark.parametrize("scale", [NAN, -1.0, 0.0, INF, "1", None])
    def test_initialize_state_scene_scale(self, scale):
        with pytest.raises(ValueError, match=r"^scene_scale: expected a finite number > 0, got"):
            VisibilityAwareDensification().initialize_state(scene_scale=scale)
        with pytest.raises(ValueError, match=r"^scene_scale: expected a finite number > 0, got"):
            DefaultStrategy().initialize_state(scale)

    def test_initialize_state_valid(self):
        state = VisibilityAwareDensification().initialize_state(np.float64(2.5))
        assert state["scene_scale"] == 2.5 and state["vad_priors"] == {}


class _NoBase:
    """A base strategy that reads nothing (as gsplat's MCMCStrategy): only the VAD-GS checks run."""

    def initialize_state(self, scene_scale: float = 1.0) -> dict:
        return {}

    def step_pre_backward(self, *args, **kwargs) -> None:
        pass

    def step_post_backward(self, *args, **kwargs) -> None:
        pass


@pytest.fixture(scope="module")
def inputs(tiny_scene):
    return VisibilityInputs.from_scene(tiny_scene)


@pytest.fixture(scope="module")
def index(inputs):
    """A coarse visibility index of the tiny scene, built once."""
    return VisibilityAwareDensification(voxel_size=1.0, cell_size=20.0).prepare(inputs)


@pytest.fixture
def strategy(index):
    """A strategy with inputs, index and context (no event in reach), and its state."""
    s = VisibilityAwareDensification(base=_NoBase())
    ctx = StrategyContext(render=lambda v: None, total_steps=100, steps_per_cycle=10)
    s.prepare(context=ctx, index=index)
    return s, s.initialize_state(1.0)


def _post(strategy, info):
    s, state = strategy
    s.step_post_backward({}, {}, state, 0, info)


class TestInfo:
    def test_valid_info_passes(self, strategy, inputs):
        v = inputs.train_views[0]
        h, w = inputs.size(v)
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

    def test_depth_and_alpha_shapes(self, strategy, inputs):
        v = inputs.train_views[0]
        h, w = inputs.size(v)
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


class TestGeometryTargets:
    def test_before_prepare(self):
        s = VisibilityAwareDensification()
        with pytest.raises(ValueError, match=r"^geometry_targets: .* call prepare\(inputs, context\)"):
            s.geometry_targets({}, 0)

    def test_state_not_from_initialize_state_and_view_out_of_range(self, inputs, index):
        s = VisibilityAwareDensification(voxel_size=1.0, cell_size=20.0)
        s.prepare(inputs, index=index)
        with pytest.raises(
            ValueError, match=r"^state: expected the strategy's state .*'vad_priors'.*, got keys \[\]"
        ):
            s.geometry_targets({}, 0)
        state = s.initialize_state(1.0)
        n = inputs.num_views
        with pytest.raises(
            ValueError,
            match=rf"^view: expected an integer in \[0, {n - 1}\] \(a view of the inputs' {n}\), got {n}$",
        ):
            s.geometry_targets(state, n)
        v = inputs.train_views[0]
        targets = s.geometry_targets(state, v)
        assert targets is None or not math.isnan(float(targets.depth.sum()))
