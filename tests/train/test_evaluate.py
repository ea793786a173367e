from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from vadgs.data.lidar import lidar_depth_map
from vadgs.data.scene import LidarFrame
from vadgs.geometry.camera import backproject_depth, invert_rigid
from vadgs.train.init import InitConfig, init_gaussians
from vadgs.train.results import evaluate as ev
from vadgs.train.results.evaluate import evaluate, evaluate_split, split_views


@pytest.fixture(scope="module")
def model(tiny_scene):
    torch.manual_seed(0)
    return init_gaussians(tiny_scene, InitConfig(voxel_size=1.0, max_points=500, sh_degree=0))


def with_novel(scene, groups: dict[str, list[int]]):
    """The scene with copies of some of its views as novel views (their own index, a group)."""
    views = list(scene.views)
    for name, ids in groups.items():
        for v in ids:
            views.append(dataclasses.replace(scene.views[v], index=len(views), group=name))
    return dataclasses.replace(scene, views=views)


class TestEvaluateSplit:
    def test_test_split_is_evaluate(self, model, tiny_scene):
        out = evaluate_split(model, tiny_scene, "test", with_lpips=False)
        assert list(out) == ["test"]
        assert out["test"] == evaluate(model, tiny_scene, with_lpips=False)

    def test_novel_groups(self, model, tiny_scene):
        a, b = tiny_scene.test_views[:2], tiny_scene.test_views[2:5]
        scene = with_novel(tiny_scene, {"shift+2.0": a, "shift-2.0": b})
        assert scene.test_views == tiny_scene.test_views  # novel copies stay out of the test split
        out = evaluate_split(model, scene, "novel", with_lpips=False)
        assert list(out) == ["shift+2.0", "shift-2.0"]
        assert out["shift-2.0"].num_views == 3
        # a novel view at the pose of a test view gives that view's numbers
        ref = evaluate(model, tiny_scene, b, with_lpips=False)
        assert out["shift-2.0"].psnr == ref.psnr and out["shift-2.0"].depth == ref.depth
        assert out["shift-2.0"].psnr_star == ref.psnr_star

    def test_exceptions(self, model, tiny_scene):
        with pytest.raises(ValueError, match="no novel views"):
            evaluate_split(model, tiny_scene, "novel")
        with pytest.raises(ValueError, match="split"):
            split_views(tiny_scene, "train")


def with_render_depth(monkeypatch, depth_of):
    """Make :func:`evaluate` score the depth ``depth_of(scene, view)`` as the render's (colour kept)."""
    real = ev.render_test_view

    def fake(model, scene, view, config=None):
        out = real(model, scene, view, config)
        return out._replace(raster=out.raster._replace(depth=depth_of(scene, view)))

    monkeypatch.setattr(ev, "render_test_view", fake)


def gt_sweeps(scene, camera: str):
    """The scene with each test frame's sweep made of its ``camera`` view's dense depth, back-projected.

    Each point lies on a pixel centre of that view at its ground-truth z: projected into the view, the
    sweep is the dense ground truth on every pixel that has some.
    """
    sweeps = {}
    for v in scene.test_views:
        if scene.views[v].camera != camera:
            continue
        gtd = scene.load_depths([v])
        cams = scene.cameras([v])
        world = backproject_depth(gtd, cams.K, invert_rigid(cams.world_to_cam))[0]
        points = world.permute(1, 2, 0)[gtd[0, 0] > 0]
        sweeps[scene.views[v].frame] = LidarFrame(
            points, torch.zeros(len(points), dtype=torch.int64), torch.zeros(3)
        )

    def loader(frame: int) -> LidarFrame:
        if frame not in sweeps:
            raise FileNotFoundError(f"no LiDAR for frame {frame}")
        return sweeps[frame]

    return dataclasses.replace(scene, lidar_loader=loader)


class TestLidarDepth:
    """The ``lidar`` depth group: rendered depth against the test frames' own LiDAR sweeps."""

    def test_render_of_the_sweep_scores_zero_and_a_scaled_one_its_factor(
        self, model, tiny_scene, monkeypatch
    ):
        pixels = sum(int((lidar_depth_map(tiny_scene, v) > 0).sum()) for v in tiny_scene.test_views)
        assert pixels > 1000
        for factor, absrel, delta in [
            (1.0, 0.0, 1.0),
            (1.1, 0.1, 0.0),
            (1.04, 0.04, 1.0),
        ]:
            with_render_depth(monkeypatch, lambda s, v, f=factor: lidar_depth_map(s, v) * f)
            got = evaluate(model, tiny_scene, with_lpips=False).depth["lidar"]
            assert got["absrel"] == pytest.approx(absrel, abs=2e-5), factor
            assert got["delta_1.05"] == delta and got["pixels"] == pixels, factor

    def test_nothing_rendered_counts_as_wrong(self, model, tiny_scene, monkeypatch):
        with_render_depth(monkeypatch, lambda s, v: torch.zeros(1, 1, *s.image_size(v)))
        got = evaluate(model, tiny_scene, with_lpips=False).depth["lidar"]
        assert got["absrel"] == 1.0 and got["delta_1.05"] == 0.0

    def test_agrees_with_the_dense_group_on_the_same_pixels(self, model, tiny_scene):
        """A sweep made of the front views' dense ground truth: ``lidar`` == ``all`` there (a real render)."""
        scene = gt_sweeps(tiny_scene, "front")
        front = [v for v in scene.test_views if scene.views[v].camera == "front"]
        got = evaluate(model, scene, front, with_lpips=False).depth
        assert (
            got["lidar"]["pixels"]
            == got["all"]["pixels"]
            == 2 * 60 * 36 - sum(int((scene.load_depths([v]) <= 0).sum()) for v in front)
        )
        assert got["lidar"]["absrel"] == pytest.approx(got["all"]["absrel"], abs=2e-5)
        assert got["lidar"]["delta_1.05"] == pytest.approx(
            got["all"]["delta_1.05"], abs=1 / got["all"]["pixels"]
        )
        assert 0.05 < got["all"]["absrel"] < 1  # a real render, not a perfect one

    def test_dense_groups_unchanged_and_no_lidar_group_without_sweeps(self, model, tiny_scene):
        with_lidar = evaluate(model, tiny_scene, with_lpips=False)
        without = evaluate(model, dataclasses.replace(tiny_scene, lidar_loader=None), with_lpips=False)
        assert "lidar" in with_lidar.depth and "lidar" not in without.depth
        assert {k: g for k, g in with_lidar.depth.items() if k != "lidar"} == without.depth
        assert sorted(without.depth) == ["all", "sign", "upper_facade"]
        # a view whose frame has no sweep adds nothing; no view with one: no group
        first = tiny_scene.test_frames[0]
        one = dataclasses.replace(
            tiny_scene, lidar_loader=lambda f: tiny_scene.lidar(f) if f == first else tiny_scene.lidar(-1)
        )
        with pytest.raises(FileNotFoundError):
            one.lidar(tiny_scene.test_frames[1])
        expected = sum(
            int((lidar_depth_map(tiny_scene, v) > 0).sum())
            for v in tiny_scene.test_views
            if tiny_scene.views[v].frame == first
        )
        assert 0 < expected < with_lidar.depth["lidar"]["pixels"]
        assert evaluate(model, one, with_lpips=False).depth["lidar"]["pixels"] == expected
        none = dataclasses.replace(tiny_scene, lidar_loader=lambda f: tiny_scene.lidar(-1))
        assert "lidar" not in evaluate(model, none, with_lpips=False).depth

    def test_dense_ground_truth_against_the_bundled_sweeps(self, model, tiny_scene, monkeypatch):
        """The sample's own LiDAR is no perfect reference: a render of the dense ground truth is off on it.

        Points hidden from the camera behind a nearer surface (LiDAR-camera parallax) and the nearest
        point of a coarse pixel: docs/evaluation.md gives the figures.
        """
        with_render_depth(monkeypatch, lambda s, v: s.load_depths([v]))
        got = evaluate(model, tiny_scene, with_lpips=False).depth
        assert got["all"]["absrel"] == 0.0 and got["all"]["delta_1.05"] == 1.0
        rel, ratio = [], []
        for v in tiny_scene.test_views:  # the reference, pixel by pixel in numpy
            lid = lidar_depth_map(tiny_scene, v).numpy().ravel()
            gtd = tiny_scene.load_depths([v]).numpy().ravel()
            on = lid > 0
            rel.append(np.abs(gtd[on] - lid[on]) / lid[on])
            ratio.append(np.maximum(gtd[on] / lid[on], lid[on] / np.maximum(gtd[on], 1e-9)))
        assert got["lidar"]["pixels"] == sum(len(r) for r in rel)
        assert got["lidar"]["absrel"] == pytest.approx(np.concatenate(rel).mean(), abs=1e-5)
        assert got["lidar"]["delta_1.05"] == pytest.approx((np.concatenate(ratio) < 1.05).mean(), abs=1e-5)
        assert got["lidar"]["absrel"] > 0.02 and got["lidar"]["delta_1.05"] < 0.9


def test_a_model_on_the_device_is_scored_as_on_the_cpu(device):
    """Render on the model's device, metrics beside the ground truth on the CPU: the same figures."""
    from vadgs.data import load_scene, sample_scene_path

    scene = load_scene(sample_scene_path(), scale=0.25)
    model = init_gaussians(scene, InitConfig(voxel_size=1.0, max_points=500, sh_degree=0))
    ref = evaluate(model, scene, with_lpips=False)
    got = evaluate(model.to(device), scene, with_lpips=False)
    assert got.psnr == pytest.approx(ref.psnr, abs=1e-3)
    assert got.depth.keys() == ref.depth.keys() and "lidar" in got.depth
    for k in ref.depth:
        assert got.depth[k]["absrel"] == pytest.approx(ref.depth[k]["absrel"], abs=1e-3)
