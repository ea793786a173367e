"""The incompleteness detection of an event (:mod:`vadgs.train.vad.detect`): the loop's renders kept
in a bounded store (:func:`keep_render`), read back by :class:`EventRenders` at the event, and the
event's batched test of them (:func:`detect`) against the per-view test (:func:`detect_view`)."""

from __future__ import annotations

import dataclasses

import torch

from tests.train.vad.sample import BUILDING, sample_model, sample_trainer
from vadgs.train.vad import ReconstructConfig, ViewRender
from vadgs.train.vad.detect import EventRenders, keep_render, view_map
from vadgs.train.vad.state import compact_render, expand_render


class TestEventReusesTheLoopsRenders:
    def test_trained_views_are_not_rendered_again(self, scene, index, gt_points):
        pts, col, ins, spc = gt_points
        keep = ins != BUILDING
        trainer = sample_trainer(
            scene,
            sample_model(scene, pts[keep], col[keep], spc[keep]),
            index,
            every_cycles=10**6,
            skip_classes=("road", "sidewalk", "tree", "car", "sign"),
            reconstruct=ReconstructConfig(max_crop=96),
        )
        calls = []
        render = trainer.strategy.context.render
        for _ in range(len(trainer.train_views)):  # one cycle: every training view trained once
            trainer.train_step()
        st = trainer.state
        assert sorted(st["vad_tests"]) == sorted(trainer.train_views)
        assert sorted(st["vad_renders"]) == sorted(trainer.train_views)
        ctx = dataclasses.replace(trainer.strategy.context, render=lambda v: calls.append(v) or render(v))
        trainer.strategy.context = ctx
        # the stored tests equal fresh ones made from fresh renders up to the model's last steps
        rows_kept, views = trainer.strategy.detect(tests=st["vad_tests"], kept=st["vad_renders"])
        assert calls == []
        event = trainer.strategy.densify(trainer.model.params, trainer.optimizer, st, trainer.step)
        assert calls == [] and event["views_rendered"] == 0
        assert event["tests_reused"] == len(views)
        done = {e["instance"]: e for e in event["instances"]}
        assert done[BUILDING]["added"] > 100
        assert st["vad_tests"] == {} and st["vad_renders"] == {}  # the next event tests anew
        assert int(rows_kept.flagged[rows_kept.instance == BUILDING].sum()) >= 1

    def test_the_events_test_of_kept_renders_flags_as_the_steps_own_renders(
        self, scene, index, gt_points, monkeypatch
    ):
        """The event tests the kept renders (float16 depth, uint8 opacity), batched: the same rows
        as the old per-step test of each step's own float32 render (detect_view), flag for flag."""
        import vadgs.train.vad.strategy as strategy_module
        from vadgs.train.vad.detect import detect_view, observe_view

        pts, col, ins, spc = gt_points
        keep = (ins != BUILDING) & (ins != 10)  # two instances to flag
        trainer = sample_trainer(
            scene, sample_model(scene, pts[keep], col[keep], spc[keep]), index, every_cycles=10**6
        )
        per_step = {}

        def observe(state, info, idx, inputs, incomplete, max_bytes, num_ids=None):
            r = info["raster"]
            per_step[int(info["view"])] = detect_view(
                idx, int(info["view"]), r.depth[0], r.alpha[0], incomplete
            )
            return observe_view(state, info, idx, inputs, incomplete, max_bytes, num_ids)

        monkeypatch.setattr(strategy_module, "observe_view", observe)
        for _ in range(len(trainer.train_views)):
            trainer.train_step()
        st = trainer.state
        assert all(len(st["vad_tests"][v]) == 0 for v in trainer.train_views)  # none tested on the step
        rows, views = trainer.strategy.detect(tests=st["vad_tests"], kept=st["vad_renders"])
        assert sorted(per_step) == sorted(views)
        want = [(k, *row) for k, v in enumerate(views) for row in zip(*(
            per_step[v][i].tolist() for i in (1, 2, 6)))]  # fmt: skip
        got = list(zip(*(getattr(rows, f).tolist() for f in ("view", "instance", "flagged", "pixels"))))
        assert got == want  # the same rows in the same (view, instance) order, the same flags
        assert sum(f for *_, f, _ in got) >= 4  # flags to compare
        ratio = torch.cat([per_step[v][3] for v in views])
        fin = torch.isfinite(ratio)
        assert torch.equal(fin, torch.isfinite(rows.depth_ratio))
        # float16 depth (2^-11) may also reorder near-equal ratios: the median another pixel's (3e-3 seen)
        torch.testing.assert_close(rows.depth_ratio[fin], ratio[fin], rtol=1e-2, atol=0)

    def test_render_cache_is_bounded(self, scene, index, gt_points):
        pts, col, _, spc = gt_points
        h, w = scene.cameras([0]).image_size
        one_view = 5 * h * w  # float16 depth, uint8 alpha, two int8 octahedral codes per normal
        trainer = sample_trainer(
            scene,
            sample_model(scene, pts, col, spc),
            index,
            every_cycles=10**6,
            render_cache_mb=2.5 * one_view / 2**20,
        )
        trained, sample = [], trainer.sampler.next
        trainer.sampler.next = lambda: trained.append(sample()) or trained[-1]
        for _ in range(6):
            trainer.train_step()
        kept = trainer.state["vad_renders"]
        assert list(kept) == trained[-2:]  # the two most recent views
        tests = trainer.state["vad_tests"]
        assert len(tests) == 6  # tests are small: all kept
        # the kept ones are tested at the event, the dropped ones were tested when dropped, from
        # their kept form (find_incomplete_ids' rows, as the event's test of it would give)
        assert all((len(tests[v]) == 0) == (v in kept) for v in trained)
        dropped = trained[0]
        assert len(tests[dropped]) == 9 and bool(tests[dropped][-1].any())
        assert [(x.dtype, x.shape) for x in kept[trained[-1]]] == [
            (torch.float16, (1, h, w)),
            (torch.uint8, (1, h, w)),
            (torch.int8, (2, h, w)),
        ]


def _render(seed: int, h: int = 6, w: int = 8) -> ViewRender:
    g = torch.Generator().manual_seed(seed)
    normal = torch.nn.functional.normalize(torch.randn(3, h, w, generator=g), dim=0)
    return ViewRender(torch.rand(1, h, w, generator=g) * 10, torch.rand(1, h, w, generator=g), normal)


class TestKeepRender:
    """:func:`keep_render` alone: 5 bytes a pixel kept, the oldest dropped beyond the bound."""

    def test_the_oldest_is_dropped_beyond_the_bound(self):
        one = 5 * 6 * 8  # float16 depth, uint8 opacity, two int8 codes of the normal
        store, dropped = {}, []
        for v in (3, 1, 4):
            keep_render(store, v, _render(v), 2 * one, on_drop=lambda view, kept: dropped.append(view))
        assert list(store) == [1, 4] and dropped == [3]
        for v, kept in store.items():  # as compact_render keeps it
            assert all(torch.equal(a, b) for a, b in zip(kept, compact_render(*_render(v))))
        keep_render(store, 1, _render(9), 2 * one, on_drop=lambda view, kept: dropped.append(view))
        assert list(store) == [4, 1] and dropped == [3]  # a view's new render replaces its own
        keep_render(store, 5, _render(5), 10 * one)
        assert list(store) == [4, 1, 5]
        keep_render(store, 7, _render(7), one // 2)  # a bound below one render still keeps the newest
        assert list(store) == [7]
        keep_render(store, 7, _render(7), 0)  # none kept at a bound of 0
        assert store == {}

    def test_event_renders_read_kept_views_and_render_the_others_once(self):
        calls = []
        kept = {2: compact_render(*_render(2))}
        renders = EventRenders(lambda v: calls.append(v) or _render(v), kept)
        for v in (2, 5, 2, 5):
            out = renders(v)
        assert calls == [5] and renders.rendered == 1
        d, a, n = expand_render(kept[2])
        assert torch.equal(renders(2).depth, d) and torch.equal(renders(2).alpha, a)
        assert torch.equal(renders(2).normals, n)
        assert torch.equal(out.depth, _render(5).depth)

    def test_view_map(self):
        x = torch.rand(1, 3, 4, 5, requires_grad=True)
        assert view_map(x).shape == (3, 4, 5) and not view_map(x).requires_grad
        assert view_map(torch.rand(4, 5)).shape == (1, 4, 5)
        assert view_map(torch.rand(2, 4, 5)).shape == (2, 4, 5)
