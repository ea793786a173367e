"""The inputs of the VAD-GS strategy (:mod:`vadgs.train.vad.inputs`): :class:`VisibilityInputs` of
gsplat's ``Parser`` (the tests' Parser-like namespace of the COLMAP sample) against those of vadgs's
own COLMAP reader, and its errors."""

from __future__ import annotations

import copy

import pytest
import torch

from vadgs.data import load_colmap
from vadgs.train.vad import VisibilityInputs, build_visibility_index


@pytest.fixture(scope="module")
def project(colmap_sample):
    return colmap_sample


@pytest.fixture(scope="module")
def parser(colmap_sample_parser):
    return colmap_sample_parser


class TestInputsFromParser:
    def test_same_index_as_the_vadgs_colmap_scene(self, project, parser):
        """``from_gsplat_parser`` of the Parser-like namespace and ``from_scene`` of vadgs's own
        COLMAP reader (same model, resolution and split) give the same cameras, images, TRACK
        visibility and derived instances."""
        scene, _ = load_colmap(project / "sparse" / "0", scale=0.5, test_every=8)
        ours = VisibilityInputs.from_gsplat_parser(parser)
        theirs = VisibilityInputs.from_scene(scene)
        root = str(project / "images") + "/"
        order = [parser.image_names.index(str(v.image).split(root)[-1]) for v in scene.views]
        assert sorted(order) == list(range(24))
        assert [order[v] for v in theirs.train_views] == list(ours.train_views)  # same split
        torch.testing.assert_close(ours.cameras.K[order], theirs.cameras.K, atol=1e-4, rtol=0)
        torch.testing.assert_close(
            ours.cameras.world_to_cam[order], theirs.cameras.world_to_cam, atol=1e-4, rtol=0
        )
        assert ours.cameras.image_size == theirs.cameras.image_size == (72, 120)
        torch.testing.assert_close(ours.load_image(order[5], None), theirs.load_image(5, None))
        assert ours.sfm.points.shape == theirs.sfm.points.shape
        # the same lengths (a vadgs scene is in its units, depth 10; the parser's depth is measured)
        assert theirs.scene_depth == 10.0 and ours.scene_depth == pytest.approx(11.27, abs=0.01)
        a, b = build_visibility_index(ours, 0.5, scene_depth=10.0), build_visibility_index(theirs, 0.5)
        torch.testing.assert_close(a.grid.centers, b.grid.centers)
        for m in range(len(a.grid)):
            assert {order.index(v) for v in a.grid.views_of(m).tolist()} == set(b.grid.views_of(m).tolist())
        assert a.derives_instances and b.derives_instances
        for v in (0, 7, 13):
            assert torch.equal(a.instances(order[v]), b.instances(v)), v

    def test_errors(self, parser):
        bad = copy.copy(parser)
        bad.camtoworlds = parser.camtoworlds[:3]
        with pytest.raises(ValueError, match=r"parser.camtoworlds: expected \(24, 4, 4\), got \(3, 4, 4\)"):
            VisibilityInputs.from_gsplat_parser(bad)
