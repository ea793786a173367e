"""An event's (instance, reference) pairs matched together (issue 48 item 2), against one call per pair.

:func:`~vadgs.train.vad.event.run_event` plans every pair of a wave of instances (selection,
crops), matches all of them in few :func:`~vadgs.mvs.patchmatch` calls
(:func:`~vadgs.train.vad.matching.match_plans`: crops padded to the largest of a call, each
reference its own depth range and pixels), then fuses pair by pair. A batched call draws other
random numbers than one call per pair, so the two agree in distribution, not bit for bit: checked
here on the bundled sample at half resolution, per pair (the same crops; as many pixels matched;
depths agreeing) and per event (the same instances, references, groups and outcomes; as many
points).
"""

from __future__ import annotations

import dataclasses

import pytest
import torch

import vadgs.train.vad.event as event_module
from vadgs.train.vad.crops import MatchedCrops
from vadgs.train.vad.matching import MatchPlan, match_plans


def _trainer(match_padding):
    from vadgs.data import load_scene, sample_scene_path
    from vadgs.train.config import TrainConfig
    from vadgs.train.trainer import Trainer
    from vadgs.train.vad import ReconstructConfig, VisibilityDensifyConfig

    torch.manual_seed(0)  # the two trainers of a test train alike
    scene = load_scene(sample_scene_path(), scale=0.5)  # 18 training views
    rec = ReconstructConfig(match_padding=match_padding)
    vad = VisibilityDensifyConfig(every_cycles=10**6, work_budget=None, max_instances=2, reconstruct=rec)
    with pytest.warns(UserWarning, match="no VAD-GS event"):  # the event is called by hand below
        trainer = Trainer(scene, TrainConfig(iterations=10**6, checkpoint_every=0, vad=vad), progress=False)
    for _ in range(20):  # one full cycle: the event reuses every view's render and test
        trainer.train_step()
    return trainer


def _event(trainer):
    return trainer.strategy.densify(trainer.model.params, trainer.optimizer, trainer.state, trainer.step)


@pytest.fixture(scope="module")
def events():
    """The same event (same model, same seeds) with its pairs in one call, and one call per pair.

    The batched run records each pair's result and the same pair matched alone (same inputs).
    """
    pairs: list[tuple[MatchPlan, MatchedCrops, MatchedCrops, MatchedCrops]] = []
    calls: list[int] = []

    def batched(index, plans, config=None, render_prior=None):
        out = match_plans(index, plans, config, render_prior)
        calls.append(len(plans))
        reseeded = dataclasses.replace(config, patchmatch=dataclasses.replace(config.patchmatch, seed=1))
        for plan, got in zip(plans, out):
            (alone,) = match_plans(index, [plan], config, render_prior)
            (other_seed,) = match_plans(index, [plan], reseeded, render_prior)
            pairs.append((plan, got, alone, other_seed))
        return out

    def per_pair(index, plans, config=None, render_prior=None):
        return [match_plans(index, [plan], config, render_prior)[0] for plan in plans]

    mp = pytest.MonkeyPatch()
    try:
        mp.setattr(event_module, "match_plans", batched)
        one = _event(_trainer(None))
        mp.setattr(event_module, "match_plans", per_pair)
        each = _event(_trainer(None))
    finally:
        mp.undo()
    return one, each, pairs, calls


def test_pairs_are_matched_together(events):
    one, _, pairs, calls = events
    assert one["attempted"] == 2 and len(pairs) >= 3  # two instances, several references
    assert calls == [len(pairs)]  # one wave, all its pairs in one match_plans


def _agreement(a: MatchedCrops, b: MatchedCrops) -> tuple[int, float]:
    """Matched pixels of ``a`` minus ``b``'s, and the share of both's within 5 % of each other."""
    both = a.result.mask & b.result.mask
    rel = (a.result.depth - b.result.depth).abs() / b.result.depth.clamp_min(1e-6)
    return int(a.result.mask.sum()) - int(b.result.mask.sum()), float((rel[both] < 0.05).float().mean())


def test_each_pair_as_if_matched_alone(events):
    """The same crops and masks, matched pixels only in them; against the pair matched alone, as
    many pixels matched and depths agreeing as well as two seeds of the pair alone agree."""
    _, _, pairs, _ = events
    for plan, got, alone, other_seed in pairs:
        assert torch.equal(got.images, alone.images) and torch.equal(got.masks, alone.masks)
        assert got.result.depth.shape == alone.result.depth.shape
        assert got.result.view_costs.shape == alone.result.view_costs.shape
        assert not (got.result.mask & ~got.masks).any()
        n = int(got.masks.sum())
        more, agree = _agreement(got, alone)
        more_seed, agree_seed = _agreement(other_seed, alone)
        where = (plan.instance, plan.ref, more, agree, more_seed, agree_seed)
        assert abs(more) <= max(2 * abs(more_seed), 0.05 * n), where
        assert agree >= agree_seed - 0.1, where


def test_the_event_as_with_one_call_per_pair(events):
    """The same instances, references, groups and outcomes; the points within 15 %."""
    one, each, _, _ = events
    keys = ("instance", "class", "references", "views")
    assert [[e[k] for k in keys] for e in one["instances"]] == [
        [e[k] for k in keys] for e in each["instances"]
    ]
    assert one["outcomes"] == each["outcomes"]
    assert one["work"] == each["work"]  # a function of the crops
    for a, b in zip(one["instances"], each["instances"]):
        assert abs(a["points"] - b["points"]) <= 0.15 * b["points"], (a, b)
    assert abs(one["added"] - each["added"]) <= 0.15 * each["added"]


def test_match_padding_is_checked():
    from vadgs.train.vad import ReconstructConfig

    with pytest.raises(ValueError, match="match_padding: expected None or a finite number >= 1"):
        ReconstructConfig(match_padding=0.5)
    assert dataclasses.replace(ReconstructConfig(), match_padding=None).match_padding is None


def _inputs(b: int, h: int, w: int, v: int = 4):
    """A stand-in of one plan's PatchMatch inputs: only its shapes are read."""
    from types import SimpleNamespace

    return SimpleNamespace(images=torch.zeros(b, 3, h, w), src_images=torch.zeros(b, v, 3, 1, 1))


class TestBatches:
    def test_similar_crops_share_a_call(self):
        from vadgs.train.vad.matching import _batches

        plans = [_inputs(5, 29, 40), _inputs(5, 53, 42), _inputs(5, 24, 80), _inputs(4, 40, 61, v=3)]
        assert _batches(plans, 4.0, 2, False) == [[0, 1, 2, 3]]  # padded 53x80 <= 4 x 29x40
        assert _batches(plans, None, 2, False) == [[0, 1, 2, 3]]
        assert sorted(_batches(plans, 1.0, 2, False)) == [[0], [1], [2], [3]]

    def test_the_padded_size_counts_both_sides(self):
        from vadgs.train.vad.matching import _batches

        plans = [_inputs(3, 20, 140), _inputs(3, 140, 20)]  # padded 140x140: 7 times either
        assert sorted(_batches(plans, 4.0, 2, False)) == [[0], [1]]
        assert _batches(plans, 8.0, 2, False) == [[0, 1]]

    def test_fewer_views_than_top_k_apart_and_the_call_size_capped(self):
        from vadgs.train.vad.matching import MAX_CALL_PIXEL_VIEWS, _batches

        assert sorted(_batches([_inputs(2, 30, 30, v=1), _inputs(3, 30, 30)], None, 2, False)) == [[0], [1]]
        assert _batches([_inputs(2, 30, 30, v=1), _inputs(3, 30, 30, v=1)], None, 2, False) == [[0, 1]]
        per = 5 * 100 * 100 * 4  # pixel-views of one plan
        n = MAX_CALL_PIXEL_VIEWS // per + 1  # one plan too many for a call
        batches = _batches([_inputs(5, 100, 100) for _ in range(n)], None, 2, False)
        assert len(batches) == 2 and sum(map(len, batches)) == n
        assert all(len(b) * per <= MAX_CALL_PIXEL_VIEWS for b in batches)
