"""The static / dynamic matching regions of the paper's Sec. 4.3 (``crops.matching_region``) on the
bundled sample, against its instance maps, and the crops that use them."""

import torch

from tests.train.vad.test_vad import BUILDING, CAR
from tests.train.vad.test_vad import index as index
from tests.train.vad.test_vad import scene as scene
from vadgs.train.vad import ReconstructConfig
from vadgs.train.vad.crops import MatchScale, crop_group, matching_region


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
