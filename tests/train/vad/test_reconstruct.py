"""The steps of a VAD-GS event on their own: matching scale, point thinning, what is already
explained, the reuse of the loop's renders, the event log and its budgets (work, and the opt-in
wall-clock cap)."""

import copy
import dataclasses

import pytest
import torch

from tests.train.vad.test_vad import BUILDING, CAR, _model, _trainer
from tests.train.vad.test_vad import gt_points as gt_points
from tests.train.vad.test_vad import index as index
from tests.train.vad.test_vad import scene as scene
from vadgs.geometry.points import thin_points
from vadgs.train.vad import ReconstructConfig, VisibilityDensifyConfig
from vadgs.train.vad.crops import MatchScale, match_scale
from vadgs.train.vad.reconstruct import ViewRender, reconstruct_instance
from vadgs.train.vad.survey import instance_frame


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


class TestThinPoints:
    def test_one_point_per_cell_first_wins(self):
        g = torch.Generator().manual_seed(0)
        p = torch.rand(5000, 3, generator=g)
        keep = thin_points(p, 0.1)
        cells = torch.floor(p / 0.1).long()
        # naive reference: the first point of every occupied cell
        seen, ref = set(), []
        for c in cells.tolist():
            ref.append(tuple(c) not in seen)
            seen.add(tuple(c))
        assert keep.tolist() == ref
        assert int(keep.sum()) == len(seen) <= 1000

    def test_existing_points_take_their_cells(self):
        p = torch.tensor([[0.05, 0.05, 0.05], [0.15, 0.05, 0.05]])
        assert thin_points(p, 0.1, torch.tensor([[0.01, 0.01, 0.01]])).tolist() == [False, True]
        assert thin_points(torch.zeros(0, 3), 0.1).shape == (0,)


class TestReconstructSteps:
    def test_coarse_matching_of_a_large_facade_stays_on_it(self, scene, index, gt_points):
        """The deleted facade matched at half resolution: fewer points, still on the surface."""
        pts, _, ins, _ = gt_points
        target = pts[ins == BUILDING]
        ref = max(scene.train_views, key=lambda v: int((index.instances(v) == BUILDING).sum()))
        fine = ReconstructConfig(max_crop=96, max_match_pixels=None)
        coarse = dataclasses.replace(fine, max_match_pixels=256)
        out = {}
        for name, cfg in (("fine", fine), ("coarse", coarse)):
            rec = reconstruct_instance(index, ref, BUILDING, cfg, torch.Generator().manual_seed(0))
            assert rec.reason == "ok"
            d = torch.cdist(rec.points, target).min(1).values
            out[name] = (rec.points.shape[0], float(d.median()), float(rec.spacing.median()))
        (n_f, d_f, s_f), (n_c, d_c, s_c) = out["fine"], out["coarse"]
        assert n_c < 0.5 * n_f  # coarser scale: fewer points ...
        assert s_c > 1.5 * s_f  # ... each standing for a larger cell
        assert d_f < 0.1 and d_c < 0.25  # both on the true facade (the sample is 120x72 px)

    def test_thin_factor_widens_only_coarsely_matched_instances(self, scene, index, gt_points):
        """``thin_factor``: fewer, wider points on a large (coarsely matched) facade, still on it;
        an instance matched at the scene's resolution is untouched."""
        pts, _, ins, _ = gt_points
        target = pts[ins == BUILDING]
        ref = max(scene.train_views, key=lambda v: int((index.instances(v) == BUILDING).sum()))
        coarse = ReconstructConfig(max_crop=96, max_match_pixels=256, thin_factor=1.0)
        out = {}
        for f in (1.0, 2.0):
            cfg = dataclasses.replace(coarse, thin_factor=f)
            rec = reconstruct_instance(index, ref, BUILDING, cfg, torch.Generator().manual_seed(0))
            d = torch.cdist(rec.points, target).min(1).values
            out[f] = (rec.points.shape[0], float(d.median()), float(rec.spacing.median()))
        (n1, _, s1), (n2, d2, s2) = out[1.0], out[2.0]
        assert n2 < 0.6 * n1 and 1.6 * s1 < s2 < 2.5 * s1, out  # a quarter of the cells, twice as wide
        assert d2 < 0.25, out  # still on the true facade
        fine = ReconstructConfig(max_crop=96, max_match_pixels=None)
        a, b = (
            reconstruct_instance(index, ref, BUILDING, dataclasses.replace(fine, thin_factor=f),
                                 torch.Generator().manual_seed(0))
            for f in (1.0, 2.0)
        )  # fmt: skip
        assert torch.equal(a.points, b.points) and torch.equal(a.spacing, b.spacing)
        with pytest.raises(ValueError, match="thin_factor: expected a finite number >= 1"):
            ReconstructConfig(thin_factor=0.5)

    def test_explained_pixels_give_no_points(self, scene, index, gt_points):
        """Where the render already shows an opaque surface at the MVS depth, nothing is added."""
        ref = max(scene.train_views, key=lambda v: int((index.instances(v) == BUILDING).sum()))
        cfg = ReconstructConfig(max_crop=96, max_match_pixels=None)
        depths = scene.load_depths()

        def perfect(v):  # a render that explains everything: ground-truth depth, opaque
            d = depths[v]
            return ViewRender(d, torch.ones_like(d), torch.zeros(3, *d.shape[-2:]))

        def empty(v):
            d = torch.zeros_like(depths[v])
            return ViewRender(d, d, torch.zeros(3, *d.shape[-2:]))

        g = torch.Generator
        explained = reconstruct_instance(index, ref, BUILDING, cfg, g().manual_seed(0), perfect)
        missing = reconstruct_instance(index, ref, BUILDING, cfg, g().manual_seed(0), empty)
        assert missing.points.shape[0] > 200
        assert explained.points.shape[0] < 0.1 * missing.points.shape[0]
        # the priors are kept either way
        assert sum(int((d > 0).sum()) for d in explained.depth) > 0.5 * sum(
            int((d > 0).sum()) for d in missing.depth
        )


class TestEventReusesTheLoopsRenders:
    def test_trained_views_are_not_rendered_again(self, scene, index, gt_points):
        pts, col, ins, spc = gt_points
        keep = ins != BUILDING
        trainer = _trainer(
            scene,
            _model(scene, pts[keep], col[keep], spc[keep]),
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
        trainer = _trainer(scene, _model(scene, pts[keep], col[keep], spc[keep]), index, every_cycles=10**6)
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
        trainer = _trainer(
            scene,
            _model(scene, pts, col, spc),
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


def _slow_clock(monkeypatch) -> None:
    """The VAD-GS strategy's clock reads 1000 s more at every call (a very loaded machine)."""
    import vadgs.train.vad.event as event_module  # the event's clock (the `time` module: the strategy's too)

    ticks = iter(range(10**9))
    monkeypatch.setattr(event_module.time, "perf_counter", lambda: 1000.0 * next(ticks))


def _incomplete_model(scene, gt_points):
    """The sample's ground-truth surface without the facade and instance 10: what an event repairs."""
    pts, col, ins, spc = gt_points
    keep = (ins != BUILDING) & (ins != 10)
    return _model(scene, pts[keep], col[keep], spc[keep])


class TestCooldown:
    """``cooldown_events``: an instance reconstructed at an event waits that many events; one never
    reconstructed is never cooling down (was: skipped in early events when ``cooldown_events >= 10``,
    a ``-10`` sentinel for "never")."""

    @pytest.mark.parametrize("cooldown", [0, 12])
    def test_first_event_attempts_and_the_next_waits(self, scene, index, gt_points, cooldown):
        trainer = _trainer(
            scene,
            _incomplete_model(scene, gt_points),
            index,
            work_budget=None,
            max_instances=1,
            cooldown_events=cooldown,
            reconstruct=ReconstructConfig(max_crop=64),
        )
        st = trainer.state
        first = trainer.strategy.densify(trainer.model.params, trainer.optimizer, st, 0)
        assert first["attempted"] == 1 and "cooldown" not in first["skipped"]
        done = first["instances"][0]["instance"]
        assert st["vad_last_done"] == {done: 0}
        second = trainer.strategy.densify(trainer.model.params, trainer.optimizer, st, 1)
        attempted = {e["instance"] for e in second["instances"]}
        if cooldown:  # event 1 - 0 <= 12: the instance done waits, the others do not
            assert done not in attempted
        assert second["attempted"] == 1


class TestEventLog:
    def test_log_counts_and_time_budget(self, scene, index, gt_points):
        trainer = _trainer(
            scene,
            _incomplete_model(scene, gt_points),
            index,
            work_budget=None,
            time_budget=1e-9,  # the opt-in wall-clock cap: the first instance only, then cut
            reconstruct=ReconstructConfig(max_crop=64),
        )
        st = trainer.state
        st["vad_train_s"] = 100.0
        event = trainer.strategy.densify(trainer.model.params, trainer.optimizer, st, 0)
        assert event["attempted"] == 1
        assert event["candidates"] >= 2
        assert event["skipped"].get("time_budget", 0) == event["candidates"] - 1
        assert event["budget_s"] == pytest.approx(1e-7)
        assert event["work_budget"] is None
        log = st["pending_log"][-1]
        assert "wall-clock cap" in log["summary"] and "skipped" in log["summary"]
        assert event["flagged_instances"] >= event["candidates"]
        assert event["repaired"] <= event["attempted"]
        (first,) = event["instances"]  # its consistent MVS points, thinned to the Gaussians added
        assert first["points"] > first["added"] > 0, first
        assert event["total_s"] >= event["mvs_s"] > 0

    def test_work_budget_counts_patchmatch_work(self, scene, index, gt_points, monkeypatch):
        """The budget is PatchMatch pixel-sweeps per training pixel so far, whatever the clock says."""
        model = _incomplete_model(scene, gt_points)
        events = []
        for clock in (None, "slow"):
            if clock == "slow":  # every reading 1000 s after the last: a very loaded machine
                _slow_clock(monkeypatch)
            trainer = _trainer(
                scene,
                copy.deepcopy(model),
                index,
                work_budget=0.1,
                skip_classes=("road", "car"),
                reconstruct=ReconstructConfig(max_crop=64),
            )
            st = trainer.state
            events.append(trainer.strategy.densify(trainer.model.params, trainer.optimizer, st, 9))
        plain, slow = events
        pixels = 10 * 144 * 240  # steps 0..9 of the sample's 240x144 views
        assert plain["work_budget"] == pytest.approx(0.1 * pixels)
        # cut by work, mid-event: every instance started within the budget, the last one went over
        assert 2 <= plain["attempted"] < plain["candidates"]
        assert plain["skipped"]["work_budget"] == plain["candidates"] - plain["attempted"]
        work = [e["work"] for e in plain["instances"]]
        assert sum(work[:-1]) <= plain["work_budget"] < sum(work) == plain["work"]
        assert "work budget" in trainer.state["pending_log"][-1]["summary"]
        assert slow["total_s"] >= 1000 and slow["budget_s"] is None  # no wall-clock cap by default
        same = ("attempted", "skipped", "added", "work", "instances")
        assert {k: plain[k] for k in same} == {k: slow[k] for k in same}

    def test_same_model_under_a_slow_clock(self, monkeypatch):
        """One config and seed, one model: training with a clock 1000x slower gives the same bits."""
        from vadgs.data import load_scene, sample_scene_path
        from vadgs.train.config import TrainConfig
        from vadgs.train.trainer import Trainer

        scene = load_scene(sample_scene_path(), scale=0.5)  # 120x72: 18 views, the event after step 17
        small = ReconstructConfig(max_crop=32)
        vad = VisibilityDensifyConfig(every_cycles=1, work_budget=0.2, reconstruct=small)
        cfg = TrainConfig(iterations=40, checkpoint_every=10**6, vad=vad)
        runs = []
        for slow in (False, True):
            if slow:  # each reading 1000 s after the last: the event and every step take "hours"
                _slow_clock(monkeypatch)
            trainer = Trainer(scene, cfg, progress=False)
            for _ in range(19):
                trainer.train_step()
            runs.append(trainer)
        (plain,), (late,) = (t.state["vad_events"] for t in runs)
        assert late["total_s"] >= 1000 and runs[1].state["vad_train_s"] >= 10_000
        assert 2 <= plain["attempted"] < plain["candidates"]  # the budget cut this event
        assert plain["skipped"].get("work_budget") == plain["candidates"] - plain["attempted"]
        assert (late["attempted"], late["skipped"], late["work"]) == (
            plain["attempted"],
            plain["skipped"],
            plain["work"],
        )
        a, b = (t.model.params for t in runs)
        assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)

    def test_no_cap_by_default(self):
        cfg = VisibilityDensifyConfig()
        assert cfg.max_instances is None and cfg.time_budget is None and cfg.work_budget == 0.1
        for name in ("work_budget", "time_budget"):
            with pytest.raises(ValueError, match=f"{name}: expected None or a finite number > 0, got 0"):
                VisibilityDensifyConfig(**{name: 0})

    def test_match_work(self):
        from vadgs.mvs import PatchMatchConfig
        from vadgs.train.vad.matching import match_work

        masks = torch.zeros(2, 1, 8, 8, dtype=torch.bool)
        masks[0, 0, :4] = True  # 32 + 10 reference pixels
        masks[1, 0, 0] = True
        masks[1, 0, 1, :2] = True
        one_level = PatchMatchConfig(iterations=3, pyramid_levels=1)
        assert match_work(masks, 4, one_level) == 42 * 4 * 3
        # three levels: 5 sweeps at 1/16 of the pixels, then 2 at 1/4 and 2 at full
        three = PatchMatchConfig(iterations=5, pyramid_levels=3, fine_iterations=2)
        assert match_work(masks, 1, three) == 42 * (5 / 16 + 2 / 4 + 2)


class TestViewCache:
    def test_bounded_index_gives_the_same_maps(self, scene, index):
        """A tiny byte budget drops views and recomputes them identically."""
        from vadgs.data.cache import ByteCache
        from vadgs.train.vad import build_visibility_index

        small = build_visibility_index(scene)
        small.view_cache = ByteCache(max_bytes=3 * 120 * 72 * 12)
        views = list(scene.train_views)[:8]
        for v in views + views:
            d, lab = small.voxel_depth(v)
            d0, lab0 = index.voxel_depth(v)
            assert torch.equal(d, d0) and torch.equal(lab, lab0)
            assert torch.equal(small.instances(v), index.instances(v))
        assert small.view_cache.nbytes <= small.view_cache.max_bytes
        assert len(small.view_cache.keys()) < 3 * len(views)


class TestViewsOfDifferentSizes:
    """A rig whose front-left camera is smaller (120x200 against 144x240) trains with VAD-GS."""

    def test_event_adds_gaussians_from_both_sizes(self, tmp_path):
        from tests.data.multisize_sample import write_multisize_sample
        from vadgs.data import load_scene
        from vadgs.train.config import TrainConfig
        from vadgs.train.trainer import Trainer

        sc = load_scene(write_multisize_sample(tmp_path))
        sizes = {sc.image_size(v) for v in range(sc.num_views)}
        assert sizes == {(120, 200), (144, 240)}
        vad = VisibilityDensifyConfig(
            every_cycles=1, work_budget=None, reconstruct=ReconstructConfig(max_crop=48)
        )
        trainer = Trainer(sc, TrainConfig(iterations=20, checkpoint_every=10**6, vad=vad), progress=False)
        index = trainer.strategy.prepare()
        assert index.cameras.image_size == (144, 240)
        small = next(v for v in range(sc.num_views) if sc.image_size(v) == (120, 200))
        # the smaller view's maps are padded: nothing (no voxel, no instance) outside its own area
        d, _ = index.voxel_depth(small)
        assert d.shape[-2:] == (144, 240) and not (d[0, 120:] > 0).any() and not (d[0, :, 200:] > 0).any()
        assert not index.instances(small)[120:].any() and (index.instances(small)[:120, :200] > 0).any()
        for _ in range(20):
            trainer.train_step()
        (event,) = trainer.state["vad_events"]
        refs = {r: sc.image_size(r) for e in event["instances"] if e["added"] for r in e["references"]}
        assert event["added"] > 500
        assert set(refs.values()) == sizes  # Gaussians added from references of both sizes
        # and the priors of the smaller views come back at their own size
        targets = trainer.strategy.geometry_targets(trainer.state, small)
        assert targets.depth.shape[-2:] == (120, 200)
        # evaluation and video render every view at its own size
        from vadgs.train.results.evaluate import evaluate
        from vadgs.train.results.trajectory import ego_trajectory
        from vadgs.train.results.video import render_video

        big = next(v for v in range(sc.num_views) if sc.image_size(v) == (144, 240))
        metrics = evaluate(trainer.model, sc, views=[small, big], with_lpips=False)
        assert [m["view"] for m in metrics.per_view] == [small, big]
        assert all(m["psnr"] > 10 for m in metrics.per_view)
        info = render_video(
            trainer.model, sc, tmp_path / "v.mp4", ego_trajectory(sc, "front_left"), progress=False
        )
        assert info.size[1] == 3 * 200 and info.num_frames == len(sc.frames)


class TestInstanceFrame:
    """Step 1 (``survey.instance_frame``): a moving car is matched in its object frame."""

    def test_moving_car_in_its_object_frame(self, scene, index):
        ref = max(scene.train_views, key=lambda v: int((index.instances(v) == CAR).sum()))
        frame = instance_frame(index, ref, CAR, CAR, ReconstructConfig())
        assert not isinstance(frame, str)
        covis = index.track_covis[CAR]
        assert frame.covis is covis and bool(frame.voxels.all()) and len(frame.voxels) == covis.num_voxels
        track = scene.tracks[CAR]
        cams = scene.cameras(list(range(len(scene.views))))
        checked = 0
        for v in range(len(scene.views)):
            pos = scene.frame_position(scene.views[v].frame)
            assert bool(frame.allowed[v]) == (bool(index.allowed[v]) and bool(track.valid[pos]))
            if frame.allowed[v]:  # object frame -> camera = world -> camera after the track's pose
                expected = cams.world_to_cam[v] @ track.object_to_world[pos]
                torch.testing.assert_close(frame.world_to_cam[v], expected, atol=1e-5, rtol=1e-5)
                checked += 1
        assert checked >= 5

    def test_static_instance_in_the_world(self, scene, index):
        ref = max(scene.train_views, key=lambda v: int((index.instances(v) == BUILDING).sum()))
        frame = instance_frame(index, ref, BUILDING, None, ReconstructConfig())
        assert not isinstance(frame, str)
        assert frame.covis is index.covis and torch.equal(frame.world_to_cam, index.cameras.world_to_cam)
        assert torch.equal(frame.voxels, index.labels == BUILDING)  # the facade has LiDAR voxels

    def test_a_track_without_lidar_has_nothing_to_match(self, scene, index):
        blind = dataclasses.replace(
            index, track_covis={k: c for k, c in index.track_covis.items() if k != CAR}
        )
        ref = max(scene.train_views, key=lambda v: int((index.instances(v) == CAR).sum()))
        assert instance_frame(blind, ref, CAR, CAR, ReconstructConfig()) == "no_lidar_on_track"
