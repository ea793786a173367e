"""Fixtures of the tests of :mod:`vadgs.train.vad`: the bundled sample at full scale, its visibility
index and ground-truth surface points (one of each per test module); the tiny sample's inputs and
a coarse index of them."""

from __future__ import annotations

import pytest
import torch

from vadgs.data import load_scene, sample_scene_path
from vadgs.geometry import backproject_depth
from vadgs.train.vad import VisibilityAwareDensification, VisibilityInputs, build_visibility_index


@pytest.fixture(scope="module")
def scene():
    return load_scene(sample_scene_path())


@pytest.fixture(scope="module")
def index(scene):
    return build_visibility_index(scene)


@pytest.fixture(scope="module")
def gt_points(scene):
    """Static surface points from the ground-truth depth of the training views (every 3rd pixel)."""
    views = scene.train_views
    depth = scene.load_depths(views)
    cams = scene.cameras(views)
    pts = backproject_depth(depth, cams.K, cams.cam_to_world)[:, :, ::3, ::3]
    ins = scene.load_instances(views)[:, ::3, ::3]
    img = scene.load_images(views)[:, :, ::3, ::3]
    valid = (depth[:, 0, ::3, ::3] > 0) & ~torch.isin(ins, torch.tensor(sorted(scene.tracks)))
    spacing = depth[:, 0, ::3, ::3] / cams.K[:, 0, 0, None, None] * 3
    return (
        pts.permute(0, 2, 3, 1)[valid],
        img.permute(0, 2, 3, 1)[valid],
        ins[valid],
        spacing[valid],
    )


@pytest.fixture(scope="module")
def tiny_inputs(tiny_scene):
    """The tiny sample's :class:`VisibilityInputs`."""
    return VisibilityInputs.from_scene(tiny_scene)


@pytest.fixture(scope="module")
def tiny_index(tiny_inputs):
    """A coarse visibility index of the tiny scene, built once."""
    return VisibilityAwareDensification(voxel_size=1.0, cell_size=20.0).prepare(tiny_inputs)
