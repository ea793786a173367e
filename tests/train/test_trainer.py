from __future__ import annotations

import dataclasses

import pytest
import torch

from vadgs.data.scene import ColmapPoints, Track
from vadgs.train.checkpoint import CHECKPOINT_NAME, load_checkpoint
from vadgs.train.config import TrainConfig
from vadgs.train.divergence import NonFiniteLossError
from vadgs.train.losses import GeometricLossConfig
from vadgs.train.trainer import Trainer


def _params(trainer):
    return {k: v.detach().clone() for k, v in trainer.model.params.items()}


class TestTrainer:
    def test_loss_decreases(self, tiny_scene, tiny_config):
        cfg = dataclasses.replace(
            tiny_config,
            iterations=36,
            strategy=dataclasses.replace(tiny_config.strategy, refine_start_iter=1000),
        )
        tr = Trainer(tiny_scene, cfg, progress=False)
        views = tr.train_views[:6]

        def loss():
            with torch.no_grad():
                terms = [tr.objective(0, v, tr.render_view(v), tr.render_hard_depth) for v in views]
                return sum(float(t["color"]) for t in terms)

        before = loss()
        tr.train()
        assert loss() < 0.85 * before

    def test_densification_during_training(self, tiny_scene, tiny_config):
        tr = Trainer(tiny_scene, tiny_config, progress=False)
        n0 = tr.model.num_gaussians
        changes = []
        tr.callback = lambda t, s: changes.append(dict(t.state["last_refine"]))
        tr.train()
        assert any(c.get("cloned", 0) + c.get("split", 0) > 0 for c in changes), changes
        assert tr.model.num_gaussians != n0
        for g in tr.optimizer.param_groups[:-1]:
            p = g["params"][0]
            assert p is tr.model.params[g["name"]]
            if p in tr.optimizer.state:
                assert tr.optimizer.state[p]["exp_avg"].shape == p.shape
        assert tr.state["grad2d"].shape[0] == tr.model.num_gaussians

    def test_resume_after_interruption_is_exact(self, tiny_scene, tiny_config, tmp_path):
        full = Trainer(tiny_scene, tiny_config, progress=False)
        full.train()
        ref = _params(full)

        def stop_at_5(trainer, step):
            if step == 5:
                trainer.request_stop()

        part = Trainer(tiny_scene, tiny_config, out_dir=tmp_path, progress=False, callback=stop_at_5)
        res = part.train()
        assert (res.step, res.completed, res.reason) == (5, False, "interrupted")
        assert (tmp_path / CHECKPOINT_NAME).is_file()
        resumed = Trainer.from_checkpoint(tmp_path, scene=tiny_scene, progress=False)
        assert resumed.step == 5
        res = resumed.train()
        assert res.completed and res.step == tiny_config.iterations
        got = _params(resumed)
        assert ref.keys() == got.keys()
        for k in ref:
            assert ref[k].shape == got[k].shape, k
            assert torch.equal(ref[k], got[k]), k

    def test_nan_loss_detected_with_step(self, tiny_scene, tiny_config):
        def nan_at_3(step, render, view):
            return {"bad": render.color.sum() * (float("nan") if step == 3 else 0.0)}

        tr = Trainer(tiny_scene, tiny_config, extra_losses=nan_at_3, progress=False)
        with pytest.raises(NonFiniteLossError, match="step 3") as e:
            tr.train()
        assert e.value.step == 3 and tr.step == 3

    def test_corrupt_checkpoint(self, tmp_path):
        bad = tmp_path / CHECKPOINT_NAME
        bad.write_bytes(b"not a checkpoint at all")
        with pytest.raises(ValueError, match="corrupt"):
            load_checkpoint(tmp_path)
        with pytest.raises(ValueError, match="corrupt"):
            Trainer.from_checkpoint(tmp_path)
        torch.save({"hello": 1}, bad)
        with pytest.raises(ValueError, match="not a vadgs"):
            load_checkpoint(bad)
        with pytest.raises(FileNotFoundError):
            load_checkpoint(tmp_path / "missing.pt")

    def test_scene_without_lidar_colmap_only(self, tiny_scene, tiny_config):
        lid = [tiny_scene.lidar(f) for f in tiny_scene.train_frames]
        pts = torch.cat([x.points for x in lid])[::50]
        colmap = ColmapPoints(
            pts,
            torch.full_like(pts, 0.5),
            torch.zeros(len(pts)),
            torch.arange(len(pts)),
            torch.zeros(0, dtype=torch.long),
            torch.zeros(0, dtype=torch.long),
            torch.zeros(0, 2),
        )
        scene = dataclasses.replace(tiny_scene, lidar_loader=None)
        cfg = dataclasses.replace(tiny_config, iterations=3)
        with pytest.raises(ValueError, match="no LiDAR"):
            Trainer(scene, cfg, progress=False)
        tr = Trainer(scene, cfg, colmap_points=colmap, progress=False)
        assert tr.model.node_counts()[f"track_{tr.model.track_ids[0]}"] == 0
        assert tr.train().completed

    def test_frames_without_tracks(self, tiny_scene, tiny_config):
        tid = sorted(tiny_scene.tracks)[0]
        t = tiny_scene.tracks[tid]
        valid = t.valid.clone()
        valid[: len(valid) // 2] = False
        tracks = dict(tiny_scene.tracks)
        tracks[tid] = Track(t.id, t.class_name, t.size_lwh, t.object_to_world, valid, t.mesh)
        scene = dataclasses.replace(tiny_scene, tracks=tracks)
        tr = Trainer(scene, dataclasses.replace(tiny_config, iterations=4), progress=False)
        k = tr.model.track_ids.index(tid)
        assert not bool(
            torch.isin(tr.model.gaussians_at(0).ids, torch.nonzero(tr.model.node_ids == k)[:, 0]).any()
        )
        assert tr.train().completed

    def test_moving_car_stays_attached(self, tiny_scene, tiny_config):
        tr = Trainer(tiny_scene, dataclasses.replace(tiny_config, iterations=6), progress=False)
        tr.train()
        model = tr.model
        tid = max(model.track_ids, key=lambda t: model.node_counts()[f"track_{t}"])
        k = model.track_ids.index(tid)
        frames = [f.index for f in tiny_scene.frames]
        centres = []
        for fi in (0, len(frames) - 1):
            g = model.gaussians_at(fi)
            sel = model.node_ids[g.ids] == k
            o2w = model.object_to_world[k, fi]
            local = model.params["means"][model.node_ids == k]
            assert torch.allclose(g.means[sel], local @ o2w[:3, :3].T + o2w[:3, 3], atol=1e-5)
            centres.append(g.means[sel].detach().mean(0))
            # the node, rendered alone, covers the car's pixels in a view where the car is visible
            views = [v for v in tiny_scene.frames[fi].view_ids]
            inst = tiny_scene.load_instances(views)
            v = views[int((inst == tid).flatten(1).sum(1).argmax())]
            car = tiny_scene.load_instances([v])[0] == tid
            assert int(car.sum()) > 5
            cams = tiny_scene.cameras([v])
            from vadgs.render import rasterize_gaussians

            with torch.no_grad():
                r = rasterize_gaussians(
                    g.means[sel],
                    g.quats[sel],
                    g.scales[sel],
                    g.opacities[sel] * 0 + 0.9,
                    torch.ones(int(sel.sum()), 3),
                    cams.world_to_cam,
                    cams.K,
                    cams.image_size,
                )
            covered = r.alpha[0, 0] > 0.5
            assert float((covered & car).sum() / car.sum()) > 0.5
        track = tiny_scene.tracks[tid]
        moved = (track.object_to_world[-1, :3, 3] - track.object_to_world[0, :3, 3]).norm()
        assert float((centres[1] - centres[0]).norm()) == pytest.approx(float(moved), rel=0.05, abs=0.05)

    def test_config_roundtrip_and_errors(self):
        c = TrainConfig().replace(**{"init.max_points": 7, "iterations": 5})
        assert c.init.max_points == 7 and TrainConfig.from_dict(c.to_dict()) == c
        with pytest.raises(ValueError, match="unknown"):
            TrainConfig.from_dict({"bogus": 1})
        with pytest.raises(ValueError, match="unknown"):
            TrainConfig().replace(**{"init.bogus": 1})


class TestHardDepth:
    def test_stride_one_is_the_opaque_render(self, tiny_scene, tiny_config):
        config = dataclasses.replace(tiny_config, geometry=GeometricLossConfig(hard_stride=1))
        tr = Trainer(tiny_scene, config, progress=False)
        v = tr.train_views[0]
        with torch.no_grad():
            full = tr.render_view(v, opacity_override=1.0).raster.depth
            assert torch.equal(tr.render_hard_depth(v), full)

    def test_fused_render_gives_the_same_depth(self, tiny_scene, tiny_config):
        """``objective.render_hard_depth``'s two ways: the step's own pass and a second render."""
        config = dataclasses.replace(tiny_config, geometry=GeometricLossConfig(hard_stride=1))
        tr = Trainer(tiny_scene, config, progress=False)
        v = tr.train_views[0]
        with torch.no_grad():
            step_render = tr.render_view(v, hard_depth=True)
            fused = tr.render_hard_depth(v, 1, step_render)
            apart = tr.render_hard_depth(v, 1)
            assert fused is step_render.raster.hard_depth
            assert float((apart > 0).float().mean()) > 0.3
            torch.testing.assert_close(fused, apart, atol=1e-4, rtol=1e-4)
            with pytest.raises(ValueError, match=r"^stride: expected 1 with a fused render"):
                tr.render_hard_depth(v, 2, step_render)
            with pytest.raises(ValueError, match=r"^fused: expected a render made with hard_depth=True"):
                tr.render_hard_depth(v, 1, tr.render_view(v))

    def test_strided_render_is_the_full_render_at_those_pixels(self, tiny_scene, tiny_config):
        config = dataclasses.replace(tiny_config, geometry=GeometricLossConfig(hard_stride=2))
        tr = Trainer(tiny_scene, config, progress=False)
        v = tr.train_views[0]
        with torch.no_grad():
            full = tr.render_view(v, opacity_override=1.0).raster.depth
            half = tr.render_hard_depth(v)
        h, w = full.shape[-2:]
        assert half.shape[-2:] == ((h + 1) // 2, (w + 1) // 2)
        sub = full[..., ::2, ::2]
        both = (sub > 0) & (half > 0)
        assert both.float().mean() > 0.5
        rel = ((half - sub).abs() / sub)[both]
        # the same surfaces at the same pixels (only the footprints' pixel blur differs)
        assert rel.median() < 0.02, float(rel.median())

    def test_loss_compares_the_targets_at_the_strided_pixels(self):
        from vadgs.train import losses as L

        target = torch.arange(1.0, 1.0 + 5 * 7).reshape(1, 1, 5, 7)
        t = L.GeometryTargets(depth=target)
        w = L.geometric_weights(0, 10)
        hard = target[..., ::2, ::2].clone()
        d = torch.zeros(1, 1, 5, 7)
        terms = L.geometric_losses(t, d, torch.zeros(1, 3, 5, 7), w, hard, hard_stride=2)
        assert float(terms["hard"]) == 0.0
        terms = L.geometric_losses(t, d, torch.zeros(1, 3, 5, 7), w, hard * 2, hard_stride=2)
        assert float(terms["hard"]) > 0
        with pytest.raises(ValueError, match="hard_depth: expected spatial size"):
            L.geometric_losses(t, d, torch.zeros(1, 3, 5, 7), w, hard, hard_stride=1)

    def test_objective_sums_a_few_prior_pixels_over_the_share(self, tiny_scene, tiny_config):
        """The step's soft and normal terms on 12 prior pixels: divided by min_prior_share of the view's."""
        from vadgs.train import losses as L

        v = tiny_scene.train_views[0]
        h, w = tiny_scene.image_size(v)
        depth, normal = torch.zeros(1, 1, h, w), torch.zeros(1, 3, h, w)
        depth[..., 2:5, 3:7] = 5.0
        normal[:, 2, 2:5, 3:7] = -1.0
        targets = L.GeometryTargets(depth=depth, normal=normal)
        terms = {}
        for share in (0.0, 0.5):
            config = dataclasses.replace(tiny_config, geometry=GeometricLossConfig(min_prior_share=share))
            tr = Trainer(tiny_scene, config, progress=False, geometry_targets=lambda _: targets)
            with torch.no_grad():
                out = tr.render_view(v)
                terms[share] = tr.objective(10**6, v, out, lambda *_: torch.zeros(()))  # past the hard term
        assert "hard" not in terms[0.5] and terms[0.0]["soft"] > 0 and terms[0.0]["normal"] > 0
        for name in ("soft", "normal"):
            torch.testing.assert_close(terms[0.5][name], terms[0.0][name] * 12 / (0.5 * h * w))

    def test_bad_stride(self):
        with pytest.raises(ValueError, match="hard_stride: expected an integer >= 1, got 0"):
            TrainConfig(geometry=GeometricLossConfig(hard_stride=0))


def test_a_step_reads_the_device_once_itself(tiny_scene, tiny_config, monkeypatch):
    """The trainer's own reads of tensor values in a step (each a synchronisation on a GPU): every
    logged number and the finiteness of the loss and the parameters together (9 before, one per
    term and parameter; then 3: the loss's finiteness before ``backward``, the parameters' after the
    update, the logged numbers). The renderer's, the strategy's and torch's own reads are not
    counted."""
    import traceback

    tr = Trainer(tiny_scene, tiny_config, progress=False)
    tr.train_step()
    where: list[str] = []
    for name in ("__bool__", "__int__", "__float__", "__index__", "item", "tolist"):
        orig = getattr(torch.Tensor, name)

        def counted(t, *a, _orig=orig, **k):
            stack = traceback.extract_stack()[:-1]  # torch's own reads (Adam's step counts) are not ours
            if "/vadgs/" in stack[-1].filename:  # a shared check (vadgs/checks.py) reads for its caller
                caller = next(f for f in reversed(stack) if not f.filename.endswith("/vadgs/checks.py"))
                where.append(f"{caller.filename.rsplit('/vadgs/', 1)[-1]}:{caller.lineno}")
            return _orig(t, *a, **k)

        monkeypatch.setattr(torch.Tensor, name, counted)
    res = tr.train_step()
    own = [w for w in where if w.startswith("train/trainer.py:")]
    assert len(own) == 1, own
    assert {"color", "total", "psnr"} <= set(res) and all(isinstance(v, float) for v in res.values())
