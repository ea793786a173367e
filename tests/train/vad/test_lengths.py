"""VAD-GS's lengths and how they scale with the scene (:mod:`vadgs.train.vad.lengths`): every length
of :data:`LENGTHS` in proportion to the scene's depth, those set explicitly kept as given, and bad
input named."""

from __future__ import annotations

import math

import pytest

from vadgs.train.vad.lengths import LENGTHS, REFERENCE_DEPTH, scene_lengths


class TestSceneLengths:
    def test_reference_depth_gives_the_lengths_exactly(self):
        assert scene_lengths() == LENGTHS and scene_lengths(REFERENCE_DEPTH) == LENGTHS

    @pytest.mark.parametrize("depth", [0.5, 3.0, 11.27, 250.0])
    def test_each_length_in_proportion_to_the_depth(self, depth):
        got = scene_lengths(depth)
        assert got.keys() == LENGTHS.keys()
        unit = depth / REFERENCE_DEPTH
        for key, value in LENGTHS.items():  # by hand: the same length in the scene's units
            if isinstance(value, tuple):
                assert isinstance(got[key], tuple) and len(got[key]) == len(value)
                assert all(math.isclose(g, v * unit, rel_tol=1e-12) for g, v in zip(got[key], value)), key
            else:
                assert math.isclose(got[key], value * unit, rel_tol=1e-12), key
        # 1/20 of the scene: the voxel edge 0.2 m -> 1 cm at depth 0.5
        assert scene_lengths(0.5)["voxel_size"] == pytest.approx(0.01)

    def test_absolute_lengths_are_kept_and_none_is_relative(self):
        got = scene_lengths(5.0, voxel_size=0.02, cell_size=None, fallback_depth_range=(1.0, 2.0))
        assert got["voxel_size"] == 0.02 and got["fallback_depth_range"] == (1.0, 2.0)
        assert got["cell_size"] == pytest.approx(5.0)  # None: scaled as the others
        assert got["min_depth"] == pytest.approx(0.1)

    def test_bad_input_is_named(self):
        with pytest.raises(
            ValueError, match=r"^absolute: expected keys of \[.*'voxel_size'.*\], got \['voxel'\]$"
        ):
            scene_lengths(10.0, voxel=0.1)
        for depth in (0.0, -1.0, math.nan, math.inf):
            with pytest.raises(ValueError, match=r"^scene_depth: expected a finite depth > 0, got"):
                scene_lengths(depth)
