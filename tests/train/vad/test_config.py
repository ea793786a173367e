"""The settings of the VAD-GS strategy (:mod:`vadgs.train.vad.config`): every field of
:class:`VisibilityDensifyConfig` has one rule, next to the field (:func:`vadgs.checks.checked`;
``tests/test_config_rules.py`` checks every config of the package), run at construction, raising a
:class:`ValueError` naming the field, the expected and the actual (issue 39, item 5: the Python API
validates like the CLI); valid values are normalised; :class:`StrategyContext` checks its own."""

from __future__ import annotations

import numpy as np
import pytest

from tests.train.vad.config_cases import NAN, check_bad_value, field_cases
from vadgs.train.vad import StrategyContext, VisibilityDensifyConfig


class TestEveryField:
    @pytest.mark.parametrize(("name", "bad"), field_cases(VisibilityDensifyConfig))
    def test_bad_value_at_construction(self, name, bad):
        check_bad_value(VisibilityDensifyConfig, name, bad)


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

    def test_defaults_unchanged(self):
        assert VisibilityDensifyConfig() == VisibilityDensifyConfig()
        assert VisibilityDensifyConfig().skip_classes == ("road",)


class TestBudgets:
    def test_no_cap_by_default(self):
        cfg = VisibilityDensifyConfig()
        assert cfg.max_instances is None and cfg.time_budget is None and cfg.work_budget == 0.1
        for name in ("work_budget", "time_budget"):
            with pytest.raises(ValueError, match=f"{name}: expected None or a finite number > 0, got 0"):
                VisibilityDensifyConfig(**{name: 0})


class TestStrategyContext:
    def test_strategy_context(self):
        with pytest.raises(ValueError, match=r"^steps_per_cycle: expected an integer >= 1, got 0$"):
            StrategyContext(render=lambda v: None, total_steps=10, steps_per_cycle=0)
        with pytest.raises(ValueError, match=r"^total_steps: expected an integer >= 0, got 2\.5$"):
            StrategyContext(render=lambda v: None, total_steps=2.5, steps_per_cycle=1)
        with pytest.raises(ValueError, match=r"^render: expected a function"):
            StrategyContext(render=None, total_steps=10, steps_per_cycle=1)
