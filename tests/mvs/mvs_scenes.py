"""Synthetic plane scenes for the MVS tests: exact ground truth, tiny images (imported by conftest)."""

from __future__ import annotations

from pathlib import Path
from typing import NamedTuple

import pytest
import torch
import torch.nn.functional as F

from vadgs.geometry import homography_warp, plane_homography, relative_pose

SHARED = Path(__file__).resolve().parents[2].parent / "shared"


class PlaneScene(NamedTuple):
    image: torch.Tensor  # (1, 1, H, W)
    src_images: torch.Tensor  # (1, V, 1, H, W)
    K: torch.Tensor  # (1, 3, 3)
    src_K: torch.Tensor  # (1, V, 3, 3)
    world_to_cam: torch.Tensor  # (1, 4, 4)
    src_world_to_cam: torch.Tensor  # (1, V, 4, 4)
    depth: torch.Tensor  # (1, 1, H, W) ground truth
    normal: torch.Tensor  # (3,) ground-truth normal (reference camera frame)


def texture(h: int, w: int, seed: int = 0) -> torch.Tensor:
    """Band-limited random texture in [0, 1], ``(1, 1, H, W)``."""
    g = torch.Generator().manual_seed(seed)
    coarse = torch.rand(1, 1, h // 2 + 1, w // 2 + 1, generator=g)
    return F.interpolate(coarse, size=(h, w), mode="bilinear", align_corners=True)


def plane_scene(
    normal=(0.0, 0.0, -1.0),
    z0: float = 2.0,
    baselines=((0.15, 0.0, 0.0), (-0.15, 0.0, 0.0), (0.0, 0.12, 0.0)),
    size=(40, 56),
    seed: int = 0,
) -> PlaneScene:
    """A textured plane through (0, 0, z0) seen by a reference camera at the origin and sources
    translated by ``baselines`` (camera centres in the reference frame)."""
    h, w = size
    f = 0.9 * w
    K = torch.tensor([[[f, 0, (w - 1) / 2], [0, f, (h - 1) / 2], [0, 0, 1]]])
    n = torch.nn.functional.normalize(torch.tensor(normal, dtype=torch.float32), dim=0)
    d = -float(n[2]) * z0  # n . (0, 0, z0) + d = 0
    img = texture(h, w, seed)
    w2c = torch.eye(4)[None]
    srcs, s_w2c = [], []
    for c in baselines:
        T = torch.eye(4)
        T[:3, 3] = -torch.tensor(c)
        src_from_ref = relative_pose(w2c, T[None])
        H = plane_homography(K, K, src_from_ref, n[None], torch.tensor([d]))  # ref -> src
        srcs.append(homography_warp(img, torch.linalg.inv(H), (h, w)))
        s_w2c.append(T)
    ys, xs = torch.meshgrid(
        torch.arange(h, dtype=torch.float32), torch.arange(w, dtype=torch.float32), indexing="ij"
    )
    rays = torch.stack([xs, ys, torch.ones_like(xs)], -1) @ torch.linalg.inv(K[0]).T
    depth = (-d / (rays @ n))[None, None]
    v = len(baselines)
    return PlaneScene(
        img,
        torch.stack(srcs, 1),
        K,
        K[:, None].expand(1, v, 3, 3).clone(),
        w2c,
        torch.stack(s_w2c)[None],
        depth,
        n,
    )


def requires_shared(*parts: str) -> Path:
    path = SHARED.joinpath(*parts)
    if not path.exists():
        pytest.skip(f"{path} not available")
    return path
