"""The instances an event repairs first and the references it picks for each
(:mod:`vadgs.train.vad.references`), against hand-worked cases of the bundled sample."""

from __future__ import annotations

import pytest

from vadgs.train.vad import VisibilityDensifyConfig, pick_references, rank_instances


class TestRankInstances:
    def test_small_sign_is_not_starved_by_facades(self):
        # the street_a situation: many large flagged facades and one small sign
        px = {10 + i: 20_000 - 1000 * i for i in range(10)} | {61: 466}
        cls = {i: "building" for i in px} | {61: "sign"}
        assert 61 not in rank_instances(px, cls, "pixels")[:6]
        ranked = rank_instances(px, cls)
        assert ranked[:2] == [10, 61]
        assert sorted(ranked) == sorted(px)  # a permutation: nothing dropped or repeated

    def test_within_a_class_largest_first(self):
        px = {1: 5, 2: 50, 3: 500, 4: 7}
        cls = {1: "tree", 2: "tree", 3: "tree", 4: "sign"}
        assert rank_instances(px, cls) == [3, 4, 2, 1]

    def test_bad_ranking_names_the_argument(self):
        with pytest.raises(ValueError, match="ranking"):
            rank_instances({1: 3}, {}, "random")
        with pytest.raises(ValueError, match="ranking"):
            VisibilityDensifyConfig(ranking="random")


class TestPickReferences:
    def test_largest_first_then_another_camera_or_far_frame(self, scene):
        front = [v.index for v in scene.views if v.camera == "front"]
        left = [v.index for v in scene.views if v.camera == "front_left"]
        cands = [(front[0], 500), (front[1], 450), (left[0], 100), (front[4], 90)]
        assert pick_references(cands, scene, 1) == [front[0]]
        # front[1] is one frame after front[0] on the same camera: skipped for the other camera
        assert pick_references(cands, scene, 2) == [front[0], left[0]]
        assert pick_references(cands, scene, 3) == [front[0], left[0], front[4]]
        assert pick_references(cands, scene, 3, min_frame_gap=1) == [front[0], front[1], left[0]]
        assert pick_references([], scene, 2) == []

    def test_a_whole_view_replaces_the_last_reference(self, scene):
        front = [v.index for v in scene.views if v.camera == "front"]
        left = [v.index for v in scene.views if v.camera == "front_left"]
        cands = [(front[0], 500), (front[1], 450), (left[0], 100), (front[4], 90), (front[3], 80)]
        # none of the three largest shows the whole instance: the last becomes the largest whole one
        assert pick_references(cands, scene, 3, whole=[front[3]]) == [front[0], left[0], front[3]]
        # ... that keeps the frame gap to the others: front[1] does not (one frame from front[0])
        assert pick_references(cands, scene, 3, whole=[front[1]]) == [front[0], left[0], front[4]]
        assert pick_references(cands, scene, 3, whole=[left[0], front[3]]) == [front[0], left[0], front[4]]
        assert pick_references(cands, scene, 1, whole=[front[3]]) == [front[0]]  # one reference: the largest
        assert pick_references(cands, scene, 3, whole=[]) == [front[0], left[0], front[4]]
