from __future__ import annotations

import pytest
import torch

from vadgs.data import load_scene, sample_scene_path
from vadgs.train.config import TrainConfig
from vadgs.train.init import InitConfig
from vadgs.train.strategy import DefaultStrategyConfig


@pytest.fixture(scope="session")
def tiny_scene():
    """The bundled sample at 60x36 (8 frames, 3 cameras, 3 moving cars)."""
    torch.set_num_threads(2)
    return load_scene(sample_scene_path(), scale=0.25)


@pytest.fixture
def tiny_config():
    return TrainConfig(
        iterations=12,
        init=InitConfig(voxel_size=0.6, max_points=1500, max_object_points=150, sh_degree=1),
        strategy=DefaultStrategyConfig(
            refine_start_iter=3, refine_every=4, reset_every=8, max_gaussians=4000
        ),
        sh_degree_interval=5,
        checkpoint_every=0,
        log_every=1,
    )


@pytest.fixture(scope="module")
def colmap_sample(tmp_path_factory):
    """The tests' COLMAP sample (24 images of the bundled scene, 1,500 SfM points), one per module."""
    from ..data.colmap_sample import write_sample_colmap

    root = tmp_path_factory.mktemp("colmap") / "proj"
    write_sample_colmap(root, n_points=1500)
    return root


@pytest.fixture(scope="module")
def colmap_sample_parser(colmap_sample):
    """gsplat's ``Parser`` of :func:`colmap_sample` (duck-typed): half size, every 8th image held out."""
    from .gsplat_parser import sample_parser

    return sample_parser(colmap_sample, factor=2, test_every=8)
