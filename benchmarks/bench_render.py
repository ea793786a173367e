"""Benchmarks of vadgs.render (pytest-benchmark; not part of the default test run).

Run (the numbers in docs/benchmarks.md come from exactly this):

    pytest benchmarks/bench_render.py --benchmark-enable -p no:cacheprovider \
        --benchmark-columns=min,median,max,rounds --benchmark-sort=name

and, for the CPU work without the wait for a loaded machine's cores (one thread, CPU time):

    VADGS_BENCH_THREADS=1 pytest benchmarks/bench_render.py --benchmark-enable -p no:cacheprovider \
        --benchmark-columns=min,median,max,rounds --benchmark-sort=name --benchmark-timer=time.process_time

Case 1: 20k random Gaussians at 256x256 (forward; forward+backward).
Case 2: 150k Gaussians initialised from street_a LiDAR (3DGS init: isotropic scales from the
mean distance to the 3 nearest neighbours, opacity 0.1) seen by the front camera at 480x288,
forward+backward with peak memory (measured in a child process, ru_maxrss). Skipped when
../shared is absent.

In-run references, timed in the same session: the same tiled compositor differentiated by
autograd instead of the hand-written backward (``RasterConfig(backward="autograd")``), and the
hand-written backward with 16-px tiles.
"""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from vadgs.render import RasterConfig, rasterize_gaussians

if os.environ.get("VADGS_BENCH_THREADS"):  # e.g. 1 on a loaded shared machine, see the docs
    torch.set_num_threads(int(os.environ["VADGS_BENCH_THREADS"]))

SHARED = Path(os.environ.get("VADGS_SHARED", Path(__file__).resolve().parents[1] / ".." / "shared"))
STREET = SHARED / "data" / "street_a"


def random_scene(n: int = 20_000, size: int = 256, seed: int = 0):
    """Case 1: means uniform in [-1, 1]^3 seen from 3 m, f = 256 px, scales 1-4 cm (1.7-7 px)."""
    g = torch.Generator().manual_seed(seed)
    means = torch.rand(n, 3, generator=g) * 2 - 1
    quats = torch.randn(n, 4, generator=g)
    scales = torch.exp(torch.rand(n, 3, generator=g) * math.log(4) + math.log(0.01))
    opacities = torch.rand(n, generator=g) * 0.9 + 0.1
    colors = torch.rand(n, 3, generator=g)
    K = torch.tensor([[[size, 0, (size - 1) / 2], [0, size, (size - 1) / 2], [0, 0, 1.0]]])
    world_to_cam = torch.eye(4)[None].clone()
    world_to_cam[0, 2, 3] = 3.0
    return (means, quats, scales, opacities, colors, world_to_cam, K, (size, size))


def street_scene(n: int = 150_000, seed: int = 0, root: Path = STREET):
    """Case 2: 3DGS-style initialisation from the LiDAR of frames 0-2 of street_a, front camera."""
    from scipy.spatial import cKDTree

    meta = json.loads((root / "scene.json").read_text())
    pts = np.concatenate([np.load(root / meta["frames"][f]["lidar"])["points"] for f in range(3)])
    rng = np.random.default_rng(seed)
    pts = pts[rng.choice(len(pts), size=min(n, len(pts)), replace=False)].astype(np.float32)
    dist, _ = cKDTree(pts).query(pts, k=4)
    scale = np.sqrt((dist[:, 1:] ** 2).mean(1)).clip(1e-4, None)
    means = torch.from_numpy(pts)
    quats = torch.zeros(len(pts), 4)
    quats[:, 0] = 1
    scales = torch.from_numpy(scale).float()[:, None].expand(-1, 3).contiguous()
    opacities = torch.full((len(pts),), 0.1)
    colors = torch.from_numpy(rng.random((len(pts), 3), dtype=np.float32))
    view = meta["frames"][0]["views"][0]
    cam = meta["cameras"][view["camera"]]
    K = torch.tensor(cam["K"], dtype=torch.float32)[None]
    world_to_cam = torch.linalg.inv(torch.tensor(view["cam_to_world"], dtype=torch.float64)).float()[None]
    return (means, quats, scales, opacities, colors, world_to_cam, K, (cam["height"], cam["width"]))


def _forward(scene, config):
    with torch.no_grad():
        return rasterize_gaussians(*scene, config=config)


def _forward_backward(scene, config):
    params = [t.clone().requires_grad_(True) for t in scene[:5]]
    out = rasterize_gaussians(*params, *scene[5:], config=config)
    (out.color.mean() + out.depth.mean() + out.alpha.mean()).backward()
    return params


CASE1_CONFIGS = {
    "manual_tile8": RasterConfig(),
    "autograd_tile8_reference": RasterConfig(backward="autograd"),
    "manual_tile16_reference": RasterConfig(tile_size=16, chunk_size=64),
}


@pytest.fixture(scope="module")
def case1():
    return random_scene()


@pytest.mark.parametrize("name", ["manual_tile8", "manual_tile16_reference"])
def test_case1_forward(benchmark, case1, name):
    benchmark.extra_info["threads"] = torch.get_num_threads()
    benchmark.pedantic(_forward, args=(case1, CASE1_CONFIGS[name]), rounds=7, warmup_rounds=2)


@pytest.mark.parametrize("name", list(CASE1_CONFIGS))
def test_case1_forward_backward(benchmark, case1, name):
    benchmark.extra_info["threads"] = torch.get_num_threads()
    benchmark.pedantic(_forward_backward, args=(case1, CASE1_CONFIGS[name]), rounds=7, warmup_rounds=2)


_PEAK_SCRIPT = r"""
import os, resource, sys, torch
sys.path.insert(0, {bench_dir!r})
from bench_render import street_scene, _forward_backward, RasterConfig
scene = street_scene()
base = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
_forward_backward(scene, RasterConfig(backward={backward!r}))
peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
print(base, peak)
"""


def _peak_rss_mib(backward: str) -> tuple[float, float]:
    code = _PEAK_SCRIPT.format(bench_dir=str(Path(__file__).parent), backward=backward)
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    base, peak = (int(v) / 1024 for v in res.stdout.split()[-2:])  # KiB -> MiB
    return base, peak


@pytest.fixture(scope="module")
def case2():
    if not (STREET / "scene.json").is_file():
        pytest.skip("needs ../shared/data/street_a")
    return street_scene()


@pytest.mark.parametrize("backward", ["manual", "autograd"])
def test_case2_forward_backward(benchmark, case2, backward):
    base, peak = _peak_rss_mib(backward)
    benchmark.extra_info.update(
        threads=torch.get_num_threads(), peak_rss_mib=round(peak), peak_above_scene_mib=round(peak - base)
    )
    benchmark.pedantic(
        _forward_backward, args=(case2, RasterConfig(backward=backward)), rounds=3, warmup_rounds=1
    )


def test_case2_forward(benchmark, case2):
    benchmark.pedantic(_forward, args=(case2, RasterConfig()), rounds=3, warmup_rounds=1)


@pytest.mark.parametrize("case", ["case1", "case2"])
@pytest.mark.parametrize("growth", [32, 1])
def test_chunk_growth_forward_backward(benchmark, request, case, growth, monkeypatch):
    """The compositor's growing chunks (default: up to 32x ``chunk_size`` as tiles finish) against
    fixed chunks (growth 1: the compositor before), forward+backward, in the same session."""
    import vadgs.render.composite as composite

    if case == "case2" and not (STREET / "scene.json").is_file():
        pytest.skip("needs ../shared/data/street_a")
    scene = request.getfixturevalue(case)
    monkeypatch.setattr(composite, "_MAX_CHUNK_GROWTH", growth)
    benchmark.group = f"chunk growth, {case} forward+backward"
    benchmark.extra_info["threads"] = torch.get_num_threads()
    benchmark.pedantic(_forward_backward, args=(scene, RasterConfig()), rounds=9, warmup_rounds=3)
