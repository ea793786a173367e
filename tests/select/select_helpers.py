"""Helpers shared by the tests of vadgs.select (not a test module)."""

from __future__ import annotations

import importlib.util
import math
import sys
from pathlib import Path

import torch

REPO = Path(__file__).resolve().parents[2]
SHARED = REPO.parent / "shared"


def load_example(name: str = "select_street"):
    """Import ``examples/<name>.py`` as a module (the street loader lives there, in one place)."""
    key = f"_vadgs_example_{name}"
    if key in sys.modules:
        return sys.modules[key]
    spec = importlib.util.spec_from_file_location(key, REPO / "examples" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[key] = module  # dataclasses look their module up there
    spec.loader.exec_module(module)
    return module


def yaw_pose(yaw_deg: float, center: tuple[float, float, float]) -> torch.Tensor:
    """world_to_cam of an OpenCV camera at ``center`` looking along world +z turned by ``yaw`` about y."""
    a = math.radians(yaw_deg)
    rot = torch.tensor([[math.cos(a), 0.0, -math.sin(a)], [0.0, 1.0, 0.0], [math.sin(a), 0.0, math.cos(a)]])
    w2c = torch.eye(4)
    w2c[:3, :3] = rot
    w2c[:3, 3] = -rot @ torch.tensor([float(c) for c in center])
    return w2c


def random_scene(num_views: int = 12, num_voxels: int = 200, seed: int = 0, p: float = 0.4):
    """Random cameras around a cloud of voxels, each view seeing a random subset."""
    g = torch.Generator().manual_seed(seed)
    centers = torch.randn(num_voxels, 3, generator=g) * 2 + torch.tensor([0.0, 0.0, 10.0])
    w2c = torch.stack(
        [
            yaw_pose(
                float(torch.rand(1, generator=g) * 60 - 30), tuple((torch.randn(3, generator=g) * 3).tolist())
            )
            for _ in range(num_views)
        ]
    )
    visible = [torch.nonzero(torch.rand(num_voxels, generator=g) < p).squeeze(1) for _ in range(num_views)]
    return centers, visible, w2c
