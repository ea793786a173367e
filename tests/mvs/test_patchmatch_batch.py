"""PatchMatch on references of different regions and depth ranges in one call (issue 48 item 2).

An event matches all its (instance, reference) pairs in few calls: each reference keeps its own
``depth_range`` and scores only the pixels of its own ``mask`` (padded to the most of the call).
Checked against ground truth and against the same reference matched alone.
"""

from __future__ import annotations

import pytest
import torch

from vadgs.mvs import PatchMatchConfig, patchmatch

from .mvs_scenes import PlaneScene, plane_scene

CFG = PatchMatchConfig(iterations=3)


def _batch(scenes: list[PlaneScene]) -> list[torch.Tensor]:
    return [torch.cat([getattr(s, f) for s in scenes]) for f in PlaneScene._fields[:6]]


def _rel_err(depth: torch.Tensor, truth: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    return ((depth - truth).abs() / truth)[valid]


@pytest.fixture(scope="module")
def scenes() -> list[PlaneScene]:
    return [
        plane_scene(normal=(0.35, -0.25, -1.0), z0=2.0, seed=1),
        plane_scene(normal=(-0.2, 0.1, -1.0), z0=3.0, seed=2),
    ]


class TestDepthRangePerReference:
    def test_each_reference_keeps_to_its_range(self, scenes):
        """A reference whose range excludes the truth (near 2) stays in it; the other one finds it."""
        ranges = [(1.0, 10.0), (2.5, 6.0)]
        a = plane_scene(z0=2.0, seed=1)  # fronto-parallel: the truth is 2 everywhere
        res = patchmatch(*_batch([a, a]), ranges, CFG)
        assert float(res.raw_depth[1].min()) >= 2.5 * (1 - 1e-6)
        assert float(res.raw_depth[1].max()) <= 6.0 * (1 + 1e-6)
        err = _rel_err(res.depth[0], a.depth[0], res.mask[0])
        assert res.mask[0].float().mean() > 0.6 and float(err.median()) < 0.02
        # the other reference's range changes nothing of this one's result
        same = patchmatch(*_batch([a, a]), [(1.0, 10.0), (1.0, 10.0)], CFG)
        assert torch.equal(res.depth[0], same.depth[0]) and torch.equal(res.mask[0], same.mask[0])
        # the clamped reference cannot reach the truth: its depths are at least 25 % off
        assert (
            float(_rel_err(res.raw_depth[1], a.depth[0], torch.ones_like(res.mask[1])).min()) >= 0.25 - 1e-6
        )

    def test_different_ranges_as_accurate_as_alone(self, scenes):
        ranges = [(1.0, 10.0), (1.5, 12.0)]
        res = patchmatch(*_batch(scenes), ranges, CFG)
        for b, (s, r) in enumerate(zip(scenes, ranges)):
            alone = patchmatch(*_batch([s]), r, CFG)
            err_b = _rel_err(res.depth[b], s.depth[0], res.mask[b])
            err_1 = _rel_err(alone.depth[0], s.depth[0], alone.mask[0])
            assert float(err_b.median()) < 0.02 and float(err_1.median()) < 0.02
            assert abs(float(err_b.median() - err_1.median())) < 0.005
            assert abs(float(res.mask[b].float().mean() - alone.mask[0].float().mean())) < 0.1

    def test_equal_pairs_are_one_range(self, scenes):
        """One pair per reference, all equal: the call of one range, bit for bit."""
        one = patchmatch(*_batch(scenes), (1.0, 10.0), CFG)
        each = patchmatch(*_batch(scenes), [(1.0, 10.0), (1.0, 10.0)], CFG)
        as_tensor = patchmatch(*_batch(scenes), torch.tensor([[1.0, 10.0], [1.0, 10.0]]), CFG)
        assert torch.equal(one.depth, each.depth) and torch.equal(one.depth, as_tensor.depth)

    @pytest.mark.parametrize(
        ("ranges", "match"),
        [
            (
                [(1.0, 10.0)] * 3,
                r"depth_range: expected one \(near, far\) pair or one per reference \(2\), got 3",
            ),
            ([(1.0, 10.0), (5.0, 2.0)], r"depth_range: expected finite 0 < near < far, got \(5.0, 2.0\)"),
            (
                [(1.0, 10.0), (1.0, 2.0, 3.0)],
                r"depth_range: expected \(near, far\) pairs, got \(1.0, 2.0, 3.0\)",
            ),
        ],
    )
    def test_bad_ranges_are_named(self, scenes, ranges, match):
        with pytest.raises(ValueError, match=match):
            patchmatch(*_batch(scenes), ranges, CFG)


class TestOwnRegionPerReference:
    def test_regions_of_different_sizes_match_as_alone(self, scenes):
        """References of a large and a small region: each scores its own pixels (padded), as alone."""
        h, w = scenes[0].image.shape[-2:]
        masks = torch.zeros(2, 1, h, w, dtype=torch.bool)
        masks[0, :, 4:-4, 4:-4] = True  # most of the image
        masks[1, :, 12:26, 20:34] = True  # a small box
        src_masks = torch.ones(2, 3, 1, h, w, dtype=torch.bool)
        res = patchmatch(*_batch(scenes), (1.0, 10.0), CFG, mask=masks, src_masks=src_masks)
        for b, s in enumerate(scenes):
            assert not (res.mask[b] & ~masks[b]).any()  # nothing outside its own region
            alone = patchmatch(*_batch([s]), (1.0, 10.0), CFG, mask=masks[b : b + 1], src_masks=src_masks[:1])
            err_b = _rel_err(res.depth[b], s.depth[0], res.mask[b])
            err_1 = _rel_err(alone.depth[0], s.depth[0], alone.mask[0])
            assert float(err_b.median()) < 0.02 and float(err_1.median()) < 0.02
            n = int(masks[b].sum())
            assert abs(int(res.mask[b].sum()) - int(alone.mask[0].sum())) < 0.1 * n
            both = res.mask[b] & alone.mask[0]
            agree = _rel_err(res.depth[b], alone.depth[0], both) < 0.05  # two searches of ~1 % error
            assert agree.float().mean() > 0.9

    def test_an_empty_region_beside_a_full_one(self, scenes):
        h, w = scenes[0].image.shape[-2:]
        masks = torch.zeros(2, 1, h, w, dtype=torch.bool)
        masks[0] = True
        res = patchmatch(*_batch(scenes), (1.0, 10.0), CFG, mask=masks)
        assert not res.mask[1].any() and (res.cost[1] == 2).all()
        assert float(_rel_err(res.depth[0], scenes[0].depth[0], res.mask[0]).median()) < 0.02
