"""Benchmarks of the voxel z-buffer on street_a (all 120 views) against an Embree ray cast.

    pytest benchmarks/bench_zbuffer.py --benchmark-enable --benchmark-columns=min,median,max,rounds

Each round (2 per case) rasterises the static LiDAR grid of street_a (training frames, 0.2 m voxels, ~150k
voxels) into all 120 views at 480×288; ``extra_info['ms_per_view']`` is the median round divided
by 120. The Embree reference ray-casts one triangle mesh of the same boxes (BVH built once,
outside the timing). Also times voxelising 10^6 voxels with 10^7 (voxel, view) pairs over 10^3
views. Needs ../shared/data/street_a (skipped when absent), trimesh and embreex.
"""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import pytest
import torch

from vadgs.geometry import ZBufferConfig, rasterize_voxels, voxelize

sys.path.insert(0, str(Path(__file__).resolve().parent))
from zbuffer_accuracy import STREET_A, EmbreeBoxes, street_grid

needs_street_a = pytest.mark.skipif(
    not (STREET_A / "scene.json").is_file(), reason="needs ../shared/data/street_a"
)
ROUNDS = 2


@pytest.fixture(scope="module")
def street():
    scene, grid, _ = street_grid()
    return scene, grid, scene.cameras()


@pytest.fixture
def threads(request):
    n = torch.get_num_threads()
    torch.set_num_threads(request.param)
    yield request.param
    torch.set_num_threads(n)


def _per_view(benchmark, n_views: int) -> None:
    benchmark.extra_info["views"] = n_views
    benchmark.extra_info["ms_per_view"] = 1000 * benchmark.stats.stats.median / n_views


@needs_street_a
@pytest.mark.parametrize(("mode", "threads"), [("box", 1), ("plane", 1), ("box", 2)], indirect=["threads"])
def test_vadgs_zbuffer_street_a(benchmark, street, mode, threads):
    scene, grid, cams = street
    views = list(range(scene.num_views))
    cfg = ZBufferConfig(depth_mode=mode)
    rasterize_voxels(grid, cams[[0]], [0], cfg)  # warm-up
    out = benchmark.pedantic(rasterize_voxels, args=(grid, cams, views, cfg), rounds=ROUNDS, iterations=1)
    assert out.index.shape == (120, 288, 480)
    _per_view(benchmark, len(views))


@needs_street_a
@pytest.mark.skipif(importlib.util.find_spec("embreex") is None, reason="needs embreex")
def test_embree_reference_street_a(benchmark, street):
    _, grid, cams = street
    caster = EmbreeBoxes(grid.centers, grid.voxel_size)

    def cast_all():
        return [caster(cams.K[b], cams.world_to_cam[b], cams.image_size) for b in range(len(cams))]

    caster(cams.K[0], cams.world_to_cam[0], cams.image_size)  # warm-up
    out = benchmark.pedantic(cast_all, rounds=ROUNDS, iterations=1)
    assert len(out) == 120
    _per_view(benchmark, len(cams))


def test_voxelize_1e6_voxels_1e3_views(benchmark):
    """CSR visibility at scale: 10^6 voxels, 10^7 (point, view) observations over 10^3 views."""
    g = torch.Generator().manual_seed(0)
    n, per_point, views = 1_000_000, 10, 1000
    side = 100  # a 100^3 lattice: every voxel gets exactly one point
    idx = torch.randperm(side**3, generator=g)[:n]
    coords = torch.stack([idx // side**2, (idx // side) % side, idx % side], 1).float()
    points = (coords + torch.rand(n, 3, generator=g) * 0.98 + 0.01) * 0.2
    pidx = torch.arange(n).repeat_interleave(per_point)
    vidx = torch.randint(0, views, (n * per_point,), generator=g)
    grid = benchmark.pedantic(voxelize, args=(points, 0.2, (pidx, vidx), views), rounds=1, iterations=1)
    assert len(grid) == n and grid.vis_indptr[-1] == grid.vis_views.numel()
    benchmark.extra_info["pairs"] = int(grid.vis_views.numel())
