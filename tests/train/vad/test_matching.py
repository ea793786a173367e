"""The pairs' PatchMatch, batched (:mod:`vadgs.train.vad.matching`): which plans share a call (similar
crop sizes, as many views when fewer than ``top_k``, the call's size capped) and the matching's
work. The batched calls against per-pair ones on the sample: ``test_vad_end_to_end.py``."""

from __future__ import annotations

import torch

from vadgs.train.vad.matching import MAX_CALL_PIXEL_VIEWS, match_batches, match_work


def _inputs(b: int, h: int, w: int, v: int = 4):
    """A stand-in of one plan's PatchMatch inputs: only its shapes are read."""
    from types import SimpleNamespace

    return SimpleNamespace(images=torch.zeros(b, 3, h, w), src_images=torch.zeros(b, v, 3, 1, 1))


class TestBatches:
    def test_similar_crops_share_a_call(self):
        plans = [_inputs(5, 29, 40), _inputs(5, 53, 42), _inputs(5, 24, 80), _inputs(4, 40, 61, v=3)]
        assert match_batches(plans, 4.0, 2, False) == [[0, 1, 2, 3]]  # padded 53x80 <= 4 x 29x40
        assert match_batches(plans, None, 2, False) == [[0, 1, 2, 3]]
        assert sorted(match_batches(plans, 1.0, 2, False)) == [[0], [1], [2], [3]]

    def test_the_padded_size_counts_both_sides(self):
        plans = [_inputs(3, 20, 140), _inputs(3, 140, 20)]  # padded 140x140: 7 times either
        assert sorted(match_batches(plans, 4.0, 2, False)) == [[0], [1]]
        assert match_batches(plans, 8.0, 2, False) == [[0, 1]]

    def test_fewer_views_than_top_k_apart_and_the_call_size_capped(self):
        apart = [_inputs(2, 30, 30, v=1), _inputs(3, 30, 30)]
        assert sorted(match_batches(apart, None, 2, False)) == [[0], [1]]
        assert match_batches([_inputs(2, 30, 30, v=1), _inputs(3, 30, 30, v=1)], None, 2, False) == [[0, 1]]
        per = 5 * 100 * 100 * 4  # pixel-views of one plan
        n = MAX_CALL_PIXEL_VIEWS // per + 1  # one plan too many for a call
        batches = match_batches([_inputs(5, 100, 100) for _ in range(n)], None, 2, False)
        assert len(batches) == 2 and sum(map(len, batches)) == n
        assert all(len(b) * per <= MAX_CALL_PIXEL_VIEWS for b in batches)


class TestMatchWork:
    def test_match_work(self):
        from vadgs.mvs import PatchMatchConfig

        masks = torch.zeros(2, 1, 8, 8, dtype=torch.bool)
        masks[0, 0, :4] = True  # 32 + 10 reference pixels
        masks[1, 0, 0] = True
        masks[1, 0, 1, :2] = True
        one_level = PatchMatchConfig(iterations=3, pyramid_levels=1)
        assert match_work(masks, 4, one_level) == 42 * 4 * 3
        # three levels: 5 sweeps at 1/16 of the pixels, then 2 at 1/4 and 2 at full
        three = PatchMatchConfig(iterations=5, pyramid_levels=3, fine_iterations=2)
        assert match_work(masks, 1, three) == 42 * (5 / 16 + 2 / 4 + 2)
