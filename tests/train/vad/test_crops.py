"""The static / dynamic matching regions of the paper's Sec. 4.3 (``crops.matching_region``) on the
bundled sample, against its instance maps, and the crops that use them; the matching scale of an
instance (finer for small ones, coarser for large ones)."""

import dataclasses

import pytest
import torch

from tests.train.vad.sample import BUILDING, CAR
from vadgs.train.vad import ReconstructConfig
from vadgs.train.vad.crops import MatchScale, crop_group, match_scale, matching_region


def _car_view(scene, index):
    """The view that shows most of both the moving car and the static facade."""
    ins = {v: index.instances(v) for v in scene.train_views}
    return max(
        scene.train_views, key=lambda v: min(int((ins[v] == CAR).sum()), int((ins[v] == BUILDING).sum()))
    )


class TestMatchingRegion:
    def test_static_region_is_every_valid_pixel_of_no_moving_object(self, scene, index):
        v = _car_view(scene, index)
        ins = scene.load_instances([v])[0]  # the scene's own instance map, not the index's
        region = matching_region(index, v, BUILDING, None)
        assert region.shape == ins.shape and region.dtype == torch.bool
        car, building = ins == CAR, ins == BUILDING
        assert int(car.sum()) > 50 and int(building.sum()) > 50  # both in the view
        assert not region[car].any()  # the moving car is out of the static region
        assert region[building].all()  # the static facade is in it
        moving = torch.isin(ins, torch.tensor(sorted(scene.tracks)))
        assert torch.equal(region, ~moving & index.valid(v))

    def test_dynamic_region_is_the_object_alone(self, scene, index):
        v = _car_view(scene, index)
        ins = scene.load_instances([v])[0]
        region = matching_region(index, v, CAR, CAR)
        assert torch.equal(region, ins == CAR)
        assert not region[ins == BUILDING].any()

    def test_crop_group_restricts_its_sources_to_the_regions(self, scene, index):
        v = _car_view(scene, index)
        group = [v, *[u for u in scene.train_views if u != v][:3]]
        cfg = ReconstructConfig(max_upsample=1, max_match_pixels=None)  # the scene's own resolution
        for instance, track in ((CAR, CAR), (BUILDING, None)):
            crops = crop_group(index, group, instance, track, cfg, torch.device("cpu"))
            assert not isinstance(crops, str) and crops.scale == MatchScale(1, 1)
            expected = torch.stack([matching_region(index, u, instance, track) for u in group])[:, None]
            assert torch.equal(crops.regions, expected)


class TestMatchScale:
    def test_small_instances_finer_large_ones_coarser(self):
        cfg = ReconstructConfig(max_match_pixels=1000, max_downsample=4)
        assert match_scale(200, (30, 30), 2, cfg) == MatchScale(2, 1)
        assert match_scale(200, (30, 30), 1, cfg) == MatchScale(1, 1)  # not finer than the files
        assert match_scale(900, (120, 150), 2, cfg) == MatchScale(1, 1)
        assert match_scale(3000, (120, 150), 2, cfg) == MatchScale(1, 2)  # 750 px at 1/2
        assert match_scale(5000, (120, 150), 2, cfg) == MatchScale(1, 4)  # 1250 > 1000 at 1/2
        assert match_scale(10**6, (120, 150), 2, cfg) == MatchScale(1, 4)  # max_downsample
        assert match_scale(10**6, (120, 150), 2, dataclasses.replace(cfg, max_match_pixels=None)).value == 1

    def test_bad_config(self):
        with pytest.raises(ValueError, match="max_downsample"):
            ReconstructConfig(max_downsample=3)
        with pytest.raises(ValueError, match="max_match_pixels"):
            ReconstructConfig(max_match_pixels=10)
        with pytest.raises(ValueError, match="depth_margin"):
            ReconstructConfig(depth_margin=(1.5, 2.0))
