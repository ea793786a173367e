"""The settings of one instance's reconstruction (:mod:`vadgs.train.vad.reconstruct_config`): every
field of :class:`ReconstructConfig` has one rule, next to the field (:func:`vadgs.checks.checked`;
``tests/test_config_rules.py`` checks every config of the package), run at construction, raising a
:class:`ValueError` naming the field, the expected and the actual (issue 39, item 5); valid values
are normalised."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from tests.train.vad.config_cases import check_bad_value, field_cases
from vadgs.train.vad import ReconstructConfig


class TestEveryField:
    @pytest.mark.parametrize(("name", "bad"), field_cases(ReconstructConfig))
    def test_bad_value_at_construction(self, name, bad):
        check_bad_value(ReconstructConfig, name, bad)


class TestMessages:
    def test_pairs_and_choices(self):
        with pytest.raises(ValueError, match=r"^depth_margin: expected a pair \(near <= 1 <= far\)"):
            ReconstructConfig(depth_margin=(2.0, 3.0))
        with pytest.raises(ValueError, match=r"^fallback_depth_range: expected None or a pair \(lo < hi\)"):
            ReconstructConfig(fallback_depth_range=(5.0, 1.0))
        with pytest.raises(ValueError, match=r"^max_downsample: expected one of \(1, 2, 4, 8\), got 3$"):
            ReconstructConfig(max_downsample=3)

    def test_match_padding_is_checked(self):
        with pytest.raises(ValueError, match="match_padding: expected None or a finite number >= 1"):
            ReconstructConfig(match_padding=0.5)
        assert dataclasses.replace(ReconstructConfig(), match_padding=None).match_padding is None


class TestValidValues:
    def test_edge_values_accepted_and_normalised(self):
        rec = ReconstructConfig(
            depth_margin=(1, 1), fallback_depth_range=[0.1, 100], max_downsample=np.int64(8), planar=None
        )
        assert rec.depth_margin == (1.0, 1.0) and rec.fallback_depth_range == (0.1, 100.0)
        assert rec.max_downsample == 8 and type(rec.max_downsample) is int

    def test_defaults_unchanged(self):
        assert ReconstructConfig() == ReconstructConfig()
