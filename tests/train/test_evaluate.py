from __future__ import annotations

import dataclasses

import pytest
import torch

from vadgs.train.init import InitConfig, init_gaussians
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
