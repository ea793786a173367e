"""The steps of a VAD-GS event (:mod:`vadgs.train.vad.event`) against naive references and
hand-computed values: each step alone (:func:`skip_reason`, :func:`candidates`, the budget,
:func:`reconstruct_pairs`, :func:`add_reconstructions`), which instances an event skips (cooldown,
a moving object in a static model) and what its log counts; the Gaussians of a moving object join
its track's node (on the bundled sample).

The event runs for real (:func:`~vadgs.train.vad.event.run_event` through the strategy's
``densify``) on stand-ins of what it reads: the detection's rows, the index's classes and the
reconstruction of an instance (a few points, no PatchMatch), so that each rule is seen alone.
"""

from __future__ import annotations

import dataclasses
import math
from types import SimpleNamespace

import pytest
import torch

import vadgs.train.vad.event as event_module
from tests.train.vad.sample import CAR, sample_reconstruction
from vadgs.train.model import GaussianModel
from vadgs.train.vad import (
    ReconstructConfig,
    StrategyContext,
    VisibilityAwareDensification,
    VisibilityDensifyConfig,
    flat_gaussians,
)
from vadgs.train.vad.event import (
    Attempt,
    EventBudget,
    EventInputs,
    add_reconstructions,
    candidates,
    event_budget,
    over_budget,
    reconstruct_pairs,
    skip_reason,
    wave_room,
)
from vadgs.train.vad.incomplete import IncompleteInstances
from vadgs.train.vad.matching import MatchPlan
from vadgs.train.vad.reconstruct import ViewRender, reconstruct_instance
from vadgs.train.vad.state import compact_render

C0 = 0.28209479177387814  # the SH band-0 constant


# -- an event on stand-ins ---------------------------------------------------------------------------


def _rows(flagged: dict[int, int], view: int = 0) -> IncompleteInstances:
    """One view's detection: every instance of ``flagged`` (id → pixels) flagged."""
    ids = sorted(flagged)
    n = len(ids)
    f = torch.full((n,), float("nan"))
    return IncompleteInstances(
        view=torch.full((n,), view, dtype=torch.int64),
        instance=torch.tensor(ids, dtype=torch.int64),
        flagged=torch.ones(n, dtype=torch.bool),
        depth_ratio=f,
        low_alpha=f,
        foreign=f,
        pixels=torch.tensor([flagged[i] for i in ids], dtype=torch.int64),
        voxel_pixels=torch.zeros(n, dtype=torch.int64),
    )


def _splats(n: int = 4, node_ids: bool = False) -> dict[str, torch.Tensor]:
    """gsplat-layout Gaussians (no optimizer: the event's additions need none)."""
    p = {
        "means": torch.zeros(n, 3),
        "quats": torch.tensor([[1.0, 0, 0, 0]]).repeat(n, 1),
        "scales": torch.zeros(n, 3),
        "opacities": torch.zeros(n),
        "sh0": torch.zeros(n, 1, 3),
        "shN": torch.zeros(n, 0, 3),
    }
    if node_ids:
        p["node_ids"] = torch.full((n,), -1, dtype=torch.int64)
    return p


def _survey(index, instance, views, *args, **kwargs):
    """An instance cut by no view's border (what the event's plan reads of its survey)."""
    return SimpleNamespace(cut=dict.fromkeys(views, False))


def _per_reference(plan):
    """``plan_matches`` made of a per-pair ``plan(index, ref, instance, ...)``."""

    def plan_matches(index, refs, instance, *args, **kwargs):
        return [plan(index, ref, instance, *args, **kwargs) for ref in refs]

    return plan_matches


class _Event:
    """A strategy whose events see ``flagged`` (instance → pixels, every event) and reconstruct each
    instance as ``made[instance] = (points, consistent)`` (default ``(3, 7)``); ``tracks``: the
    moving instances (track id → node)."""

    def __init__(self, monkeypatch, flagged, made=None, tracks=None, **settings):
        tracks = tracks or {}
        settings = {"work_budget": None, "whole_reference": False, "ranking": "pixels", **settings}
        self.strategy = s = VisibilityAwareDensification(**settings)
        s.inputs = SimpleNamespace(
            train_views=(0,),
            tracks=dict.fromkeys(tracks),
            views=[SimpleNamespace(camera="front", frame=0)],
            lidar=None,  # no LiDAR: the priors are kept as the reconstructions give them
        )
        s.index = SimpleNamespace(
            classes=lambda: dict.fromkeys(flagged, "thing"), cut_by_border=lambda view, inst: False
        )
        s.context = StrategyContext(
            render=lambda v: pytest.fail("the event renders nothing here"),
            total_steps=100,
            steps_per_cycle=1,
            track_nodes=tracks,
        )
        self.state = s.initialize_state()
        self.calls: list[int] = []
        made = made or {}

        def reconstruct(index, ref, instance, *args, **kwargs):
            self.calls.append(instance)
            n, c = made.get(instance, (3, 7))
            return sample_reconstruction(instance, n, c, track=instance if instance in tracks else None)

        monkeypatch.setattr(event_module, "detect", lambda *a, **k: (_rows(flagged), [0]))
        monkeypatch.setattr(event_module, "survey_instance", _survey)
        # an instance's plan stands for its reconstruction (a plan that is a result is not matched)
        monkeypatch.setattr(event_module, "plan_matches", _per_reference(reconstruct))

    def run(self, params, step=0) -> dict:
        return self.strategy.densify(params, None, self.state, step)


def _naive_cooldown(order, cooldown, events, max_instances):
    """Per event, the instances attempted and how many cool down: an instance attempted at event
    ``e`` is skipped at the events ``e + 1 .. e + cooldown``; one never attempted never is."""
    last: dict[int, int] = {}
    out = []
    for e in range(events):
        waiting = [i for i in order if i in last and e - last[i] <= cooldown]
        attempted = [i for i in order if i not in waiting][:max_instances]
        for i in attempted:
            last[i] = e
        out.append((attempted, len(waiting)))
    return out


class TestCooldown:
    @pytest.mark.parametrize("cooldown", [0, 1, 2, 10, 12])
    def test_against_naive(self, monkeypatch, cooldown):
        """Three instances flagged at every event, one reconstructed per event (largest first)."""
        flagged = {7: 300, 3: 200, 9: 100}
        ev = _Event(monkeypatch, flagged, cooldown_events=cooldown, max_instances=1)
        params = _splats()
        expect = _naive_cooldown([7, 3, 9], cooldown, 16, 1)
        for e, (attempted, waiting) in enumerate(expect):
            ev.calls.clear()
            entry = ev.run(params, step=e)
            assert [i["instance"] for i in entry["instances"]] == attempted, (cooldown, e)
            assert ev.calls == attempted, (cooldown, e)
            assert entry["skipped"].get("cooldown", 0) == waiting, (cooldown, e)
        if cooldown == 12:  # the reference by hand: each in turn, then all wait until event 13
            assert [a for a, _ in expect] == [[7], [3], [9]] + [[]] * 10 + [[7], [3], [9]]
        if cooldown >= 2:  # never-attempted instances never cool down, however long the cooldown
            # (the former -10 sentinel for "never" skipped them early when cooldown_events >= 10)
            assert [a for a, _ in expect[:3]] == [[7], [3], [9]]

    def test_repaired_instance_waits_exactly_cooldown_events(self, monkeypatch):
        ev = _Event(monkeypatch, {5: 100}, cooldown_events=3)
        params = _splats()
        attempted = [bool(ev.run(params, step=e)["instances"]) for e in range(9)]
        assert attempted == [True, False, False, False, True, False, False, False, True]
        assert ev.state["vad_last_done"] == {5: 8}


class TestStaticModel:
    def test_moving_instance_skipped_without_node_ids(self, monkeypatch):
        """A static model (gsplat's, no ``node_ids``) cannot hold a moving object: its instance is
        skipped as ``static_model``, the static one is reconstructed."""
        ev = _Event(monkeypatch, {4: 100, 21: 500}, tracks={21: 0})
        params = _splats()
        entry = ev.run(params)
        assert ev.calls == [4]
        assert entry["skipped"] == {"static_model": 1}
        assert [i["instance"] for i in entry["instances"]] == [4]
        assert params["means"].shape[0] == 4 + 3

    def test_moving_instance_joins_its_node(self, monkeypatch):
        ev = _Event(monkeypatch, {4: 100, 21: 500}, made={21: (2, 5)}, tracks={21: 1})
        params = _splats(node_ids=True)
        entry = ev.run(params)
        assert ev.calls == [21, 4] and entry["skipped"] == {}
        assert params["node_ids"].tolist() == [-1] * 4 + [1, 1] + [-1] * 3  # the track's node, then static


class TestEventLog:
    def test_derived_instances_are_cells_in_the_summary(self, monkeypatch):
        """A derived instance (class "static": a ground cell, a photo set's) reads "cell 10"."""
        ev = _Event(monkeypatch, {10: 400, 11: 300}, made={10: (0, 0), 11: (4, 4)})
        ev.strategy.index.classes = lambda: {10: "static", 11: "sign"}
        ev.run(_splats())
        summary = ev.state["pending_log"][-1]["summary"]
        assert "1 added nothing (cell 10: explained)" in summary and "added to sign 11 (+4)" in summary
        assert "static 10" not in summary

    def test_points_and_added(self, monkeypatch):
        """``points``: the consistent MVS points of the instance's references; ``added``: the
        Gaussians it got (what remains once the explained points are left out and the rest thinned)."""
        ev = _Event(monkeypatch, {1: 400, 2: 300, 3: 200}, made={1: (20, 500), 2: (0, 80), 3: (0, 0)})
        params = _splats()
        entry = ev.run(params)
        got = {i["instance"]: (i["points"], i["added"], i["reason"]) for i in entry["instances"]}
        assert got == {1: (500, 20, "ok"), 2: (80, 0, "explained"), 3: (0, 0, "explained")}
        assert entry["added"] == 20 == params["means"].shape[0] - 4
        assert entry["attempted"] == 3 and entry["repaired"] == 1
        assert entry["outcomes"] == {"explained": 2, "ok": 1}
        assert "2 added nothing" in ev.state["pending_log"][-1]["summary"]

    def test_points_sum_over_references(self, monkeypatch):
        ev = _Event(monkeypatch, {1: 400}, made={1: (6, 9)}, references=1)
        assert ev.run(_splats())["instances"][0]["points"] == 9
        monkeypatch.setattr(
            event_module, "pick_references", lambda candidates, *a, **k: [0, 0]
        )  # two references of the one view: two reconstructions
        entry = ev.run(_splats())
        assert (entry["instances"][0]["points"], entry["instances"][0]["added"]) == (18, 12)


class TestRendersOfAnEvent:
    """Every render an event uses is of the Gaussians as the event began: its additions are made when
    the last instance is done, so what an instance sees does not depend on whether a view was kept
    from the loop or rendered during the event, before or after another instance's reconstruction."""

    @pytest.mark.parametrize("kept", [False, True])
    def test_later_instances_see_the_model_before_the_event(self, monkeypatch, kept):
        ev = _Event(monkeypatch, {1: 400, 2: 300, 3: 200}, made={1: (5, 5), 2: (4, 4), 3: (0, 0)})
        params = _splats()
        rendered_with: list[int] = []

        def render(view):  # a render that says how many Gaussians it saw
            rendered_with.append(params["means"].shape[0])
            n = float(params["means"].shape[0])
            return ViewRender(torch.full((1, 4, 4), n), torch.ones(1, 4, 4), torch.zeros(3, 4, 4))

        ev.strategy.context = dataclasses.replace(ev.strategy.context, render=render)
        if kept:  # the loop trained view 0 before the event: its render is kept
            ev.state["vad_renders"] = {0: compact_render(*render(0))}
        seen: list[tuple[int, float, int]] = []

        def reconstruct(index, ref, instance, config, generator, renders, **kwargs):
            seen.append((instance, float(renders(0).depth.max()), float(renders(instance + 10).depth.max())))
            n, c = {1: (5, 5), 2: (4, 4)}.get(instance, (0, 0))
            return sample_reconstruction(instance, n, c)

        # an instance's plan stands for its reconstruction (a plan that is a result is not matched)
        monkeypatch.setattr(event_module, "plan_matches", _per_reference(reconstruct))
        entry = ev.run(params)
        assert seen == [(1, 4.0, 4.0), (2, 4.0, 4.0), (3, 4.0, 4.0)]  # views 0, 11, 12, 13: the model before
        assert rendered_with == [4] * 4  # each view rendered once (view 0 kept or rendered at the first ask)
        assert params["means"].shape[0] == 4 + 5 + 4 == 4 + entry["added"]  # both added, in order
        assert torch.equal(params["means"][4:9], sample_reconstruction(1, 5, 5).points)
        assert torch.equal(params["means"][9:], sample_reconstruction(2, 4, 4).points)

    def test_on_addition_gets_the_render_before(self, monkeypatch):
        got = []
        ev = _Event(monkeypatch, {1: 400, 2: 300}, made={1: (5, 5), 2: (0, 0)})
        ev.strategy.on_addition = got.append
        params = _splats()

        def render(view):
            n = float(params["means"].shape[0])
            return ViewRender(torch.full((1, 4, 4), n), torch.ones(1, 4, 4), torch.zeros(3, 4, 4))

        ev.strategy.context = dataclasses.replace(ev.strategy.context, render=render)

        def reconstruct(index, ref, instance, config, generator, renders, **kwargs):
            renders(ref)
            return sample_reconstruction(instance, 5 if instance == 1 else 0, 5)

        # an instance's plan stands for its reconstruction (a plan that is a result is not matched)
        monkeypatch.setattr(event_module, "plan_matches", _per_reference(reconstruct))
        monkeypatch.setattr(event_module, "pick_references", lambda candidates, *a, **k: [0])
        ev.run(params)
        got = [(g["instance"], g["view"], g["added"], float(g["depth"].max())) for g in got]
        assert got == [(1, 0, 5, 4.0)]
        assert params["means"].shape[0] == 9


# -- each step alone ---------------------------------------------------------------------------------


class TestSkipReason:
    CFG = VisibilityDensifyConfig(cooldown_events=2, skip_classes=("sky", "vegetation"))

    def reason(self, instance, has_nodes=True, last_done=None, event=5):
        classes = {1: "sky", 2: "car", 3: "sign", 4: "vegetation"}
        return skip_reason(instance, self.CFG, classes, {2, 4}, has_nodes, last_done or {}, event)

    def test_rules_by_hand(self):
        assert [self.reason(i) for i in (1, 2, 3, 4, 99)] == ["skip_class", None, None, "skip_class", None]
        assert self.reason(2, has_nodes=False) == "static_model"  # a moving one in a static model
        assert self.reason(3, has_nodes=False) is None  # a static one: the model holds it
        assert self.reason(4, has_nodes=False) == "skip_class"  # the class rule first

    def test_cooldown_is_inclusive_and_never_for_the_never_done(self):
        # reconstructed at event 3, cooldown 2: waits at events 4 and 5, attempted at 6
        assert [self.reason(3, last_done={3: 3}, event=e) for e in (4, 5, 6)] == [
            "cooldown",
            "cooldown",
            None,
        ]
        assert self.reason(3, last_done={7: 5}, event=5) is None  # another instance's


class TestCandidates:
    def test_against_naive(self):
        g = torch.Generator().manual_seed(3)
        n = 40
        inst = torch.randint(0, 6, (n,), generator=g)
        view = torch.randint(0, 4, (n,), generator=g)
        pixels = torch.randint(1, 500, (n,), generator=g)
        flagged = torch.rand(n, generator=g) < 0.6
        f = torch.full((n,), float("nan"))
        rows = IncompleteInstances(view, inst, flagged, f, f, f, pixels, torch.zeros(n, dtype=torch.int64))
        views = [10, 11, 12, 13]
        reasons = {2: "cooldown", 5: "skip_class"}
        got = candidates(rows, views, reasons.get)
        kept: dict[int, list[tuple[int, int]]] = {}
        skipped: dict[str, int] = {}
        for k in range(n):  # row by row
            i = int(inst[k])
            if not flagged[k]:
                continue
            if i in reasons:
                skipped[reasons[i]] = skipped.get(reasons[i], 0) + (
                    i not in kept and i not in kept.get(-i, [])
                )
                kept.setdefault(-i, []).append(i)  # seen: counted once
                continue
            kept.setdefault(i, []).append((views[int(view[k])], int(pixels[k])))
        kept = {i: v for i, v in kept.items() if i >= 0}
        assert got.views == kept
        assert got.skipped == skipped and set(skipped) == {"cooldown", "skip_class"}
        assert got.rows == int(flagged.sum())
        assert got.instances == len(set(inst[flagged].tolist()))
        assert got.best_pixels() == {i: max(px for _, px in v) for i, v in kept.items()}


class TestBudget:
    def test_event_budget_by_hand(self):
        cfg = VisibilityDensifyConfig(work_budget=3.0, time_budget=0.5)
        assert event_budget(cfg, 1000.0, 60.0) == EventBudget(3000.0, 30.0)
        off = VisibilityDensifyConfig(work_budget=None, time_budget=None)
        assert event_budget(off, None, 60.0) == EventBudget(math.inf, math.inf)
        with pytest.raises(ValueError, match=r"EventInputs.trained_pixels: expected a number .* got None"):
            event_budget(cfg, None, 60.0)

    @pytest.mark.parametrize(
        ("max_instances", "time_budget", "repaired", "room"),
        [
            (None, None, 5, math.inf),
            (3, None, 1, 2),
            (3, None, 3, 0),
            (3, 0.5, 1, 1),
            (None, 0.5, 0, 1),
            (2, 0.5, 2, 0),
        ],
    )
    def test_wave_room(self, max_instances, time_budget, repaired, room):
        cfg = VisibilityDensifyConfig(max_instances=max_instances, time_budget=time_budget)
        assert wave_room(cfg, repaired) == room

    def test_over_budget(self, monkeypatch):
        clock = iter([100.0, 100.0, 131.0])
        monkeypatch.setattr(event_module.time, "perf_counter", lambda: next(clock))
        budget = EventBudget(work=50.0, seconds=30.0)
        assert over_budget(budget, 51.0, 100.0) == "work_budget"  # the clock not read: it is not spent
        assert over_budget(budget, 50.0, 100.0) is None  # at the budget: not past it
        assert over_budget(budget, 10.0, 100.0) is None
        assert over_budget(budget, 10.0, 100.0) == "time_budget"  # 31 s > 30 s
        assert next(clock, None) is None


def _plan(ref: int, instance: int, work: float) -> MatchPlan:
    fields = dict.fromkeys(MatchPlan._fields)
    return MatchPlan(**{**fields, "ref": ref, "instance": instance, "work": work})


class TestReconstructPairs:
    def test_matched_together_finished_in_order_away_from_the_points_taken(self, monkeypatch):
        """Every plan of the wave matched in one call; each pair finished with the points the wave's
        earlier pairs took in its frame (the world, or the moving instance's own)."""
        matched_calls, finished = [], []

        def match_plans(index, plans, config, renders):
            matched_calls.append([(p.instance, p.ref) for p in plans])
            return [f"matched {p.instance}/{p.ref}" for p in plans]

        def finish_match(index, plan, matched, config, generator, renders, occupied=None):
            finished.append((matched, None if occupied is None else occupied[:, 0].tolist()))
            return sample_reconstruction(plan.instance, 0, 0)._replace(
                points=torch.full((2, 3), float(plan.ref))
            )

        monkeypatch.setattr(event_module, "match_plans", match_plans)
        monkeypatch.setattr(event_module, "finish_match", finish_match)
        nothing = sample_reconstruction(4, 0, 0)  # a pair with nothing to match: its result as planned
        wave = [
            Attempt(1, [5, 6], [_plan(5, 1, 1.0), _plan(6, 1, 2.0)]),
            Attempt(4, [7], [nothing]),
            Attempt(21, [8], [_plan(8, 21, 4.0)]),  # moving: its own frame
            Attempt(3, [9], [_plan(9, 3, 8.0)]),
        ]
        ev = SimpleNamespace(
            index=None, reconstruct=None, generator=None, inputs=SimpleNamespace(tracks={21: 0})
        )
        occupied: dict = {}
        recs = reconstruct_pairs(ev, wave, lambda v: None, occupied)
        assert matched_calls == [[(1, 5), (1, 6), (21, 8), (3, 9)]]
        assert finished == [
            ("matched 1/5", None),
            ("matched 1/6", [5.0, 5.0]),
            ("matched 21/8", None),  # the world's points are not in its frame
            ("matched 3/9", [5.0, 5.0, 6.0, 6.0]),
        ]
        assert [len(r) for r in recs] == [2, 1, 1, 1] and recs[1][0] is nothing
        assert sorted(occupied, key=str) == [21, None] and len(occupied[None]) == 3
        assert (wave[0].work, wave[1].work) == (3.0, nothing.work)  # the plans' work, summed


class TestAddReconstructions:
    def test_one_hop_to_the_model(self):
        """The rows appended are :func:`flat_gaussians` of each reconstruction, in order, on the
        node of its track; the optimizer's moments follow."""
        params = {
            "means": torch.zeros(2, 3),
            "quats": torch.tensor([[1.0, 0, 0, 0]]).repeat(2, 1),
            "log_scales": torch.zeros(2, 3),
            "opacity_logits": torch.zeros(2),
            "sh_dc": torch.zeros(2, 1, 3),
            "sh_rest": torch.zeros(2, 3, 3),
            "node_ids": torch.tensor([-1, 0]),
            "provenance": torch.zeros(2, dtype=torch.int64),
        }
        params = {k: torch.nn.Parameter(v, requires_grad=v.is_floating_point()) for k, v in params.items()}
        opt = {"means": torch.optim.Adam([params["means"]], lr=0.1)}
        params["means"].grad = torch.ones(2, 3)
        opt["means"].step()
        cfg = VisibilityDensifyConfig(new_opacity=0.3, flatness=0.5)
        ev = EventInputs(None, None, None, None, cfg, None, track_nodes={21: 1, 30: 0}, trained_pixels=None)
        moving, static = sample_reconstruction(21, 3, 3, track=21), sample_reconstruction(4, 2, 2)
        adds = [(21, 0, moving), (4, 0, static)]
        add_reconstructions(
            ev, params, opt, None, adds, lambda v: pytest.fail("no render without on_addition"), 7, 0
        )
        expect = [flat_gaussians(params, r, None, 0.3, 0.5, 7, n) for r, n in ((moving, 1), (static, -1))]
        assert params["means"].shape[0] == 2 + 3 + 2
        for k in params:
            want = torch.cat([expect[0][k], expect[1][k]]).to(params[k].dtype)
            assert torch.equal(params[k][2:].detach(), want), k
        assert params["node_ids"].tolist() == [-1, 0, 1, 1, 1, -1, -1]
        assert params["provenance"].tolist() == [0, 0] + [7] * 5
        assert torch.equal(opt["means"].state[params["means"]]["exp_avg"][2:], torch.zeros(5, 3))

    def test_max_instances_counts_the_repaired(self, monkeypatch):
        """One counter: an instance that adds nothing uses up no ``max_instances`` slot."""
        ev = _Event(monkeypatch, {1: 400, 2: 300, 3: 200}, made={1: (0, 5)}, max_instances=1)
        entry = ev.run(_splats())
        assert [i["instance"] for i in entry["instances"]] == [1, 2]
        assert (entry["attempted"], entry["repaired"], entry["added"]) == (2, 1, 3)
        assert entry["skipped"] == {"max_instances": 1}


class TestAddReconstructionsOfATrack:
    def test_new_gaussians_join_the_track_node(self, scene, index):
        ref = max(scene.train_views, key=lambda v: int((index.instances(v) == CAR).sum()))
        rec = reconstruct_instance(
            index, ref, CAR, ReconstructConfig(max_crop=64), torch.Generator().manual_seed(1)
        )
        t = scene.tracks[CAR]
        f = len(scene.frames)
        model = GaussianModel(
            torch.zeros(1, 3),
            torch.rand(1, 3),
            torch.zeros(1, 3),
            torch.full((1,), -1),
            t.object_to_world[None],
            t.valid[None],
            [CAR],
            sh_degree=0,
        )
        ctx = StrategyContext(lambda v: None, total_steps=1, steps_per_cycle=1, track_nodes={CAR: 0})
        vad = VisibilityAwareDensification()
        vad.prepare(context=ctx, index=index)
        ev = EventInputs(index, vad.inputs, ctx.render, None, vad.config, None, ctx.track_nodes, None)
        add_reconstructions(ev, model.params, None, None, [(CAR, ref, rec)], ctx.render, 1, 0)
        assert model.num_gaussians == 1 + rec.points.shape[0]
        assert (model.node_ids[1:] == 0).all()
        # the node's means are stored in the object frame and moved by the track's pose
        fpos = f - 1
        g = model.gaussians_at(fpos)
        o2w = t.object_to_world[fpos]
        expect = rec.points @ o2w[:3, :3].T + o2w[:3, 3]
        assert torch.allclose(g.means[g.ids >= 1].detach(), expect, atol=1e-4)
