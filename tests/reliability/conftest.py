from __future__ import annotations

import pytest
import torch

from vadgs.data import load_scene, sample_scene_path
from vadgs.train.init import InitConfig
from vadgs.train.strategy import DefaultStrategyConfig
from vadgs.train.trainer import TrainConfig


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
