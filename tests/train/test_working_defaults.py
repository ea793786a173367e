"""Working defaults on a CPU (issue 32): resolution, schedule of short runs, progress, checkpoint size."""

from __future__ import annotations

import dataclasses
import io
import json
import warnings

import pytest
import torch

from vadgs.cli import main
from vadgs.data import export_scene, load_scene, sample_scene_path
from vadgs.data.resolution import working_resolution, working_scale
from vadgs.train.checkpoint import CHECKPOINT_NAME, load_checkpoint
from vadgs.train.config import TrainConfig, refine_steps, scale_schedule
from vadgs.train.trainer import Trainer
from vadgs.train.vad import ReconstructConfig, VisibilityDensifyConfig, pack_state, unpack_state

pycolmap = pytest.importorskip("pycolmap")  # optional: vadgs imports it lazily (COLMAP export)

FAST_MVS = ReconstructConfig(max_crop=40)  # small crops: an event in seconds


def _colmap_model(folder, sizes):
    """A COLMAP model with one registered image per camera size ``(w, h)`` (no image files)."""
    rec = pycolmap.Reconstruction()
    for i, (w, h) in enumerate(sizes, start=1):
        cam = pycolmap.Camera.create_from_model_name(i, "PINHOLE", 0.8 * w, w, h)
        rec.add_camera_with_trivial_rig(cam)
        img = pycolmap.Image(name=f"{i}.jpg", camera_id=i, image_id=i)
        rec.add_image_with_trivial_frame(img, pycolmap.Rigid3d())
    folder.mkdir(parents=True)
    rec.write(str(folder))
    return folder


class TestWorkingResolution:
    def test_factor_is_a_power_of_two_to_1024_px(self):
        got = [working_scale(n) for n in (480, 1024, 1025, 1600, 2048, 4032, 6000)]
        assert got == [1.0, 1.0, 0.5, 0.5, 0.5, 0.25, 0.125]
        with pytest.raises(ValueError, match="longest, side"):
            working_scale(0)

    def test_colmap_largest_camera_decides(self, tmp_path):
        model = _colmap_model(tmp_path / "p" / "sparse" / "0", [(2400, 1600), (800, 600)])
        r = working_resolution(tmp_path / "p", "colmap")
        assert (r.scale, r.size, r.full) == (0.25, (400, 600), (1600, 2400))
        assert "resolution: 600x400 (--scale 0.25 of 2400x1600" in r.describe()
        assert working_resolution(model, "colmap").scale == 0.25

    def test_each_size_is_named_with_its_photos(self, tmp_path):
        """Photos upright and sideways: the line names each size at the factor, and how many have it."""
        sizes = [(4032, 3024)] * 3 + [(3024, 4032), (1600, 1200)]
        r = working_resolution(_colmap_model(tmp_path / "p" / "sparse" / "0", sizes), "colmap")
        assert r.counts == (((756, 1008), 3), ((1008, 756), 1), ((300, 400), 1)) and r.unit == "photos"
        assert r.describe().startswith(
            "resolution: 1008x756 (--scale 0.25 of 4032x3024: the working resolution, longest side "
            "<= 1024 px); 3 sizes: 1008x756 (3 photos), 756x1008 (1), 400x300 (1); --scale 1 trains"
        )
        one = working_resolution(_colmap_model(tmp_path / "q" / "sparse" / "0", [(640, 480)] * 2), "colmap")
        assert one.counts == (((480, 640), 2),) and "sizes" not in one.describe()
        # a rig counts cameras (the sample: three cameras of 240x144)
        assert working_resolution(sample_scene_path(), "benchmark").counts == (((72, 120), 3),)

    def test_rendered_benchmark_keeps_half_a_converted_scene_is_not_halved(self, tmp_path):
        sample = working_resolution(sample_scene_path(), "benchmark")
        assert (sample.scale, sample.size) == (0.5, (72, 120))
        # a converted scene (no ground-truth depth) already at 240x144: trained as it is
        export_scene(load_scene(sample_scene_path()), tmp_path / "conv", lidar=False)
        conv = working_resolution(tmp_path / "conv", "benchmark")
        assert (conv.scale, conv.size) == (1.0, (144, 240))

    def test_cli_default_and_explicit_scale(self, tmp_path, capsys):
        scene = tmp_path / "conv"
        export_scene(load_scene(sample_scene_path(), scale=0.5), scene)  # "converted at --scale 0.5"
        tiny = ["--iterations", "1", "--no-progress", "--init.max-points", "300"]
        assert main(["train", str(scene), "--out", str(tmp_path / "a"), *tiny]) == 0
        assert "resolution: 120x72 (--scale 1 of 120x72" in capsys.readouterr().out
        assert load_checkpoint(tmp_path / "a").scene_ref["scale"] == 1.0
        assert main(["train", str(scene), "--out", str(tmp_path / "b"), "--scale", "0.5", *tiny]) == 0
        # an explicit --scale chooses nothing, but the line still gives the pixel size (issue 39)
        assert "resolution: 60x36 (--scale 0.5 of 120x72: as given)" in capsys.readouterr().out
        assert load_checkpoint(tmp_path / "b").scene_ref["scale"] == 0.5


class TestShortRunSchedule:
    def test_scaled_to_iterations_default_run_unchanged(self):
        assert scale_schedule(TrainConfig()) == TrainConfig()
        assert scale_schedule(TrainConfig(iterations=30000)) == TrainConfig(iterations=30000)
        c = scale_schedule(TrainConfig(iterations=300))
        s = c.strategy
        assert (s.refine_start_iter, s.refine_every, s.refine_stop_iter, s.reset_every) == (50, 10, 1500, 300)
        assert c.sh_degree_interval == 100
        assert len(refine_steps(TrainConfig(iterations=300))) == 0  # what ran before: never densified
        assert list(refine_steps(c)) == list(range(60, 300, 10))
        s = scale_schedule(TrainConfig(iterations=30)).strategy
        assert (s.refine_start_iter, s.refine_every) == (5, 10)  # at least 10 steps of statistics

    def test_cli_scales_unless_a_flag_sets_it(self, tmp_path, capsys):
        out = tmp_path / "r"
        args = ["train", "--sample", "--scale", "0.25", "--out", str(out), "--iterations", "300",
                "--max-minutes", "1e-9", "--no-progress"]  # fmt: skip
        main(args)
        assert "short run: the schedule follows --iterations 300 (x0.1 of 3000)" in capsys.readouterr().out
        s = json.loads((out / "config.json").read_text())["config"]["strategy"]
        assert (s["refine_start_iter"], s["refine_every"], s["reset_every"]) == (50, 10, 300)
        # a schedule flag: the schedule is the caller's, as given
        main([*args[:5], str(tmp_path / "own"), *args[6:], "--strategy.refine-every", "25"])
        said = capsys.readouterr().out
        assert "short run: the schedule" not in said
        assert "WARNING: no densification in 300 steps: refine_start_iter 500, refine_every 25" in said
        s = json.loads((tmp_path / "own" / "config.json").read_text())["config"]["strategy"]
        assert (s["refine_start_iter"], s["refine_every"], s["reset_every"]) == (500, 25, 3000)
        # --resume keeps the checkpoint's schedule, says nothing
        assert main(["train", "--out", str(out), "--resume", "--max-minutes", "1e-9", "--no-progress"]) == 0
        assert "short run" not in capsys.readouterr().out

    def test_warning_when_it_can_never_densify(self, tiny_scene):
        cfg = TrainConfig(iterations=300, init=dataclasses.replace(TrainConfig().init, max_points=300))
        with pytest.warns(UserWarning, match="no densification in 300 steps: refine_start_iter 500"):
            Trainer(tiny_scene, cfg, progress=False)
        lines: list[str] = []
        Trainer(tiny_scene, cfg, progress=False, log=lines.append)
        assert len(lines) == 1 and lines[0].startswith("WARNING: no densification in 300 steps")
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            Trainer(tiny_scene, scale_schedule(cfg), progress=False)

    def test_warning_when_vad_can_never_hold_an_event(self, tiny_scene):
        """A segment's 750 training views x 5 cycles outlast the 3000 default steps: say so."""
        from vadgs.train.vad import VisibilityDensifyConfig

        n = len(tiny_scene.train_views)
        init = dataclasses.replace(TrainConfig().init, max_points=300)
        vad = VisibilityDensifyConfig()
        assert (vad.every_cycles, vad.last_event_fraction) == (5, 0.9)
        need = int((5 * n - 1) / 0.9) + 1  # the first event ends step 5n - 1, before 0.9 of the run
        cfg = scale_schedule(TrainConfig(iterations=need - 1, init=init, vad=vad))
        lines: list[str] = []
        Trainer(tiny_scene, cfg, progress=False, log=lines.append)
        assert lines == [
            f"WARNING: no VAD-GS event in {need - 1} steps: the first comes after 5 sampling cycles of the "
            f"{n} training views (step {5 * n - 1}) and none after 0.9 of the run; raise --iterations to "
            f"at least {need} or lower --vad.every-cycles"
        ]
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            Trainer(tiny_scene, dataclasses.replace(cfg, iterations=need), progress=False)


def _vad_config(scene, max_instances: int) -> TrainConfig:
    """Two sampling cycles and 4 steps: VAD-GS events after each cycle, small MVS crops."""
    cfg = TrainConfig(
        iterations=2 * len(scene.train_views) + 4,
        init=dataclasses.replace(TrainConfig().init, voxel_size=0.6, max_points=1500, max_object_points=150),
        vad=VisibilityDensifyConfig(
            every_cycles=1, time_budget=None, max_instances=max_instances, reconstruct=FAST_MVS
        ),
        checkpoint_every=0,
        checkpoint_minutes=0.0,
    )
    return scale_schedule(cfg)


@pytest.fixture(scope="module")
def vad_run(tmp_path_factory, tiny_scene):
    """A short VAD-GS run on the sample at 60x36 with two events, its messages and event lines."""
    out = tmp_path_factory.mktemp("vad")
    lines: list[str] = []
    trainer = Trainer(tiny_scene, _vad_config(tiny_scene, 2), out_dir=out, progress=False, log=lines.append)
    progress: list[str] = []
    assert trainer.strategy.on_progress is None  # the loop's bar sets it while it runs (progress=True)
    trainer.strategy.on_progress = progress.append
    trainer.additions = []
    trainer.strategy.on_addition = trainer.additions.append
    trainer.train()
    return trainer, out, lines, progress


def test_demo_figure_labels_match_the_console(vad_run):
    from vadgs.cli.demo import completion_label

    trainer, _out, lines, _progress = vad_run
    assert trainer.additions, "the run added Gaussians"
    for snap in trainer.additions:
        label, total = completion_label(snap, trainer.state["vad_events"])
        assert total >= snap["added"]
        line = next(x for x in lines if x.startswith(f"step {snap['step'] + 1}: "))
        assert f"{label} (+{total})" in line  # the console's "added to tree 50 (+2217)"


def test_priors_only_beyond_the_voxels(vad_run):
    """On a scene with LiDAR (``mvs_prior_beyond_voxels``, the default), the events keep the MVS
    depth and normals only where the view's voxel z-buffer is empty."""
    trainer, _out, _lines, _progress = vad_run
    index = trainer.strategy.prepare()
    assert trainer.strategy.config.mvs_prior_beyond_voxels and index.inputs.lidar is not None
    kept = 0
    for v, (d, n) in trainer.state["vad_priors"].items():
        reached = index.voxel_depth(v)[0].to(d.device) > 0
        assert not (d[reached] != 0).any() and not (n[reached.expand_as(n)] != 0).any(), v
        kept += int((d > 0).sum())
    assert kept > 50, kept


class TestProgress:
    def test_one_line_per_event_without_bar_and_event_progress(self, vad_run):
        trainer, _out, lines, progress = vad_run
        events = trainer.state["vad_events"]
        assert len(events) == 2
        assert len(lines) == 2 and all("visibility-aware densification" in x for x in lines)
        assert lines[0].startswith(f"step {events[0]['step'] + 1}: ")
        tested = len(trainer.train_views)
        assert progress.count(f"VAD-GS event 1: testing {tested} views") == 1
        assert f"VAD-GS event 2: testing {tested} views" in progress
        n = events[0]["candidates"]
        firsts = [x for x in progress if x.startswith("VAD-GS event 1: ") and "reconstructing 1/" in x]
        assert len(firsts) == (1 if n else 0)
        assert not n or firsts[0].startswith(f"VAD-GS event 1: {n} instances flagged, reconstructing 1/{n} (")

    def test_bar_shows_eta_loss_and_event(self, tiny_scene, monkeypatch):
        import tqdm

        from vadgs.train.strategy import DefaultStrategy

        stream = io.StringIO()
        real = tqdm.tqdm
        bars = []

        def make_bar(*a, **k):
            bars.append(real(*a, **{**k, "file": stream, "mininterval": 0}))
            return bars[-1]

        monkeypatch.setattr(tqdm, "tqdm", make_bar)

        class Talking(DefaultStrategy):  # a strategy with VAD-GS's on_progress hook
            on_progress = None

            def step_post_backward(self, *args, **kwargs):
                super().step_post_backward(*args, **kwargs)
                if args[3] == 2 and self.on_progress is not None:
                    self.on_progress("VAD-GS event 1: 4 instances flagged, reconstructing 2/4 (sign 61), 3 s")

        cfg = scale_schedule(
            TrainConfig(iterations=6, init=dataclasses.replace(TrainConfig().init, max_points=300))
        )
        strategy = Talking(cfg.strategy)
        trainer = Trainer(tiny_scene, cfg, progress=True, strategy=strategy)
        seen = []
        trainer.callback = lambda t, s: seen.append((bars[-1].postfix, bars[-1].desc))
        trainer.train()
        assert all("loss=" in p and "psnr=" in p for p, _ in seen)  # every step, not every 50
        assert seen[2][1].startswith("VAD-GS event 1: 4 instances flagged")  # the event's message
        text = stream.getvalue()
        assert "<" in text and "6/6" in text  # elapsed<remaining: the ETA
        assert strategy.on_progress is None  # the loop's hook is taken off after the run


class TestCheckpointSize:
    def test_vad_checkpoint_within_1_3x_of_the_same_model_without_vad_state(self, vad_run):
        trainer, out, _lines, _progress = vad_run
        ckpt = load_checkpoint(out)
        assert ckpt.strategy_state["vad_priors"], "the run made priors"
        size = (out / CHECKPOINT_NAME).stat().st_size
        # a baseline checkpoint at the same number of Gaussians: the standard strategy's state only
        base_state = {k: v for k, v in ckpt.strategy_state.items() if not k.startswith(("vad_", "pending"))}
        buf = io.BytesIO()
        torch.save(ckpt._replace(strategy_state=base_state)._asdict(), buf)
        ratio = size / buf.tell()
        assert ratio <= 1.3, (size, buf.tell())
        # unpacked, the same priors bit for bit; no render cache left after the last possible event
        state = unpack_state(ckpt.strategy_state)
        for v, (d, n) in trainer.state["vad_priors"].items():
            assert torch.equal(state["vad_priors"][v][0], d) and torch.equal(state["vad_priors"][v][1], n)
        assert state["vad_renders"] == {} and state["vad_tests"] == {}
        dense = sum(d.numel() + n.numel() for d, n in trainer.state["vad_priors"].values()) * 4
        packed = sum(
            x["zlib"].numel() for p in ckpt.strategy_state["vad_priors"].values() for x in p["packed"]
        )
        assert packed < dense / 2

    def test_mid_run_checkpoint_before_an_event_within_1_3x_and_resumes_exactly(
        self, tmp_path, tiny_scene, vad_run
    ):
        """Stopped one step before the first event: the render cache at its fullest (issue 32)."""
        cycle = len(tiny_scene.train_views)

        def stop(trainer, step):
            if step == cycle - 1:
                trainer.request_stop()

        Trainer(
            tiny_scene, _vad_config(tiny_scene, 2), out_dir=tmp_path, progress=False, callback=stop
        ).train()
        ckpt = load_checkpoint(tmp_path)
        renders = ckpt.strategy_state["vad_renders"]
        assert len(renders) == cycle - 1 and ckpt.strategy_state["vad_events"] == []
        size = (tmp_path / CHECKPOINT_NAME).stat().st_size
        base_state = {k: v for k, v in ckpt.strategy_state.items() if not k.startswith(("vad_", "pending"))}
        buf = io.BytesIO()
        torch.save(ckpt._replace(strategy_state=base_state)._asdict(), buf)
        # 1.082x (1.174x with the float16 renders of before): the sample's model (2650 Gaussians,
        # 2 MB) is large next to its 60x36 images; street_a's step 448 (90 views at 240x144, 92.6k
        # Gaussians): 1.247x, 1.737x before (docs/train.md)
        assert size / buf.tell() <= 1.3, (size, buf.tell())
        pixels = sum(r["packed"][0]["shape"][-1] * r["packed"][0]["shape"][-2] for r in renders.values())
        packed = sum(p["zlib"].numel() for r in renders.values() for p in r["packed"])
        assert packed / pixels < 3.0  # bytes a pixel: 2.67 (7.66 before: float16 maps, no filter)
        # resumed, the event reads the same kept renders: the run ends as the uninterrupted one
        full = vad_run[0]
        resumed = Trainer.from_checkpoint(tmp_path, scene=tiny_scene, progress=False)
        resumed.train()
        assert [e["added"] for e in resumed.state["vad_events"]] == [
            e["added"] for e in full.state["vad_events"]
        ]
        for k, v in full.model.params.items():
            assert torch.equal(v, resumed.model.params[k]), k

    def test_pack_is_lossless_with_negative_zero(self):
        # (unpacked states of older checkpoints are not read: format version 2 refuses them whole)
        d = torch.zeros(1, 5, 7)
        d[0, 2, 3], d[0, 0, 0] = 4.25, -0.0
        n = torch.randn(3, 5, 7)
        back = unpack_state(pack_state({"vad_priors": {1: (d, n)}}))["vad_priors"][1]
        assert torch.equal(back[0].view(torch.int32), d.view(torch.int32)) and torch.equal(back[1], n)
        assert unpack_state(pack_state({"grad2d": None}))["grad2d"] is None


def test_vad_resume_with_packed_priors_and_render_cache_is_exact(tmp_path, tiny_scene):
    cycle = len(tiny_scene.train_views)
    cfg = _vad_config(tiny_scene, 1)
    full = Trainer(tiny_scene, cfg, progress=False)
    full.train()

    def stop(trainer, step):
        if step == cycle + 5:  # after the first event: priors and a render cache to store
            trainer.request_stop()

    Trainer(tiny_scene, cfg, out_dir=tmp_path, progress=False, callback=stop).train()
    stored = load_checkpoint(tmp_path).strategy_state
    assert stored["vad_priors"] and len(stored["vad_renders"]) == 5
    resumed = Trainer.from_checkpoint(tmp_path, scene=tiny_scene, progress=False)
    resumed.train()
    assert len(full.state["vad_events"]) == len(resumed.state["vad_events"]) == 2
    for k, v in full.model.params.items():
        assert torch.equal(v, resumed.model.params[k]), k


def test_scene_without_lidar_says_what_to_pass(tmp_path, capsys):
    """A Waymo / nuScenes scene converted with --no-lidar: the error names --colmap and the LiDAR."""
    export_scene(load_scene(sample_scene_path(), scale=0.5), tmp_path / "conv", lidar=False)
    assert main(["train", str(tmp_path / "conv"), "--out", str(tmp_path / "r"), "--iterations", "1"]) == 2
    err = capsys.readouterr().err
    assert "nothing to initialise from: no LiDAR and no SfM points" in err
    assert "`vadgs train SCENE --colmap MODEL`" in err and "without --no-lidar" in err
