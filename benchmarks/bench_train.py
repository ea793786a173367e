"""Benchmarks of one training step with vadgs's input checks on and off, and of the hard depth
render (``GaussianModel.render_depth`` against a full render) (pytest-benchmark).

Run (the numbers in docs/benchmarks.md come from exactly this; ../shared present):

    VADGS_BENCH_THREADS=1 pytest benchmarks/bench_train.py --benchmark-enable -p no:cacheprovider \
        --benchmark-columns=min,median,max,rounds --benchmark-sort=name

The trainer of the street_a comparison (``benchmarks/street_config.json``: 240x144, ~55k
Gaussians from LiDAR, SH degree 1) with its densification held off so that every round times the
same model. "on": the default; "off": ``vadgs.checking(False)`` (what ``VADGS_CHECKS=0`` does):
no finiteness / range checks of the renderer's inputs, no NaN test of the loss and of the
parameters after the optimizer step (the loss's NaN test on the logged float stays). Both cases
alternate in one session on the same trainer; the ratio of their medians is the figure.
"""

from __future__ import annotations

import dataclasses
import json
import os
from pathlib import Path

import pytest
import torch

from vadgs import checking
from vadgs.data import load_scene
from vadgs.train.config import TrainConfig
from vadgs.train.trainer import Trainer

if os.environ.get("VADGS_BENCH_THREADS"):
    torch.set_num_threads(int(os.environ["VADGS_BENCH_THREADS"]))

HERE = Path(__file__).resolve().parent
SHARED = Path(os.environ.get("VADGS_SHARED", HERE.parents[0] / ".." / "shared"))
STREET = SHARED / "data" / "street_a"


@pytest.fixture(scope="module")
def trainer():
    if not (STREET / "scene.json").is_file():
        pytest.skip("needs ../shared/data/street_a")
    config = TrainConfig.from_dict(json.loads((HERE / "street_config.json").read_text()))
    config = dataclasses.replace(
        config, strategy=dataclasses.replace(config.strategy, refine_start_iter=10**9), checkpoint_every=0
    )
    t = Trainer(load_scene(STREET, scale=0.5), config, progress=False)
    for _ in range(3):  # warm the image and LiDAR caches of a few views
        t.train_step()
    return t


@pytest.mark.parametrize("checks", ["on", "off"])
def test_train_step(benchmark, trainer, checks):
    benchmark.group = "train step, street_a 240x144"
    with checking(checks == "on"):
        benchmark.pedantic(trainer.train_step, rounds=20, warmup_rounds=3)


def _hard_depth_full_render(trainer: Trainer, view: int) -> torch.Tensor:
    """The hard depth as it was rendered before ``GaussianModel.render_depth``: a full render
    (SH colours, sky) at the strided camera, of which only the depth is used."""
    s = trainer.config.geometry.hard_stride
    cams = trainer.scene.cameras([view])
    K = cams.K.clone()
    K[:, :2] /= s
    h, w = cams.image_size
    frame = trainer.scene.view_frame_position(view)
    size = (-(-h // s), -(-w // s))
    out = trainer.model.render(cams.world_to_cam, K, size, frame, trainer.config.raster, opacity_override=1.0)
    return out.raster.depth


@pytest.mark.parametrize("path", ["render_depth", "full render"])
def test_hard_depth_render(benchmark, trainer, path):
    """Forward and backward of the hard depth loss's render (stride ``geometry.hard_stride``, opacities 1)."""
    benchmark.group = "hard depth render + backward, street_a 240x144"
    view = trainer.train_views[0]
    render = trainer.render_hard_depth if path == "render_depth" else _hard_depth_full_render
    args = (view,) if path == "render_depth" else (trainer, view)

    def run():
        render(*args).sum().backward()
        trainer.optimizer.zero_grad(set_to_none=True)

    benchmark.pedantic(run, rounds=20, warmup_rounds=3)


@pytest.mark.parametrize("stride", [1, 2, 4])
def test_hard_depth_stride(benchmark, trainer, stride):
    """The hard depth render + backward at ``geometry.hard_stride`` 1, 2, 4 (pixel rows and columns kept)."""
    benchmark.group = "hard depth render + backward by stride, street_a 240x144"
    view = trainer.train_views[0]

    def run():
        trainer.render_hard_depth(view, stride).sum().backward()
        trainer.optimizer.zero_grad(set_to_none=True)

    benchmark.pedantic(run, rounds=20, warmup_rounds=3)


@pytest.mark.parametrize("what", ["render", "hard depth"])
@pytest.mark.parametrize("growth", [32, 1])
def test_chunk_growth(benchmark, trainer, what, growth, monkeypatch):
    """The compositor's growing chunks (default) against fixed chunks (growth 1: the compositor
    before), on the renders of a VAD-GS step: the colour render + backward of 4 training views
    (every 12th) at 240x144, and the hard depth render + backward of 2 of them."""
    import vadgs.render.composite as composite

    monkeypatch.setattr(composite, "_MAX_CHUNK_GROWTH", growth)
    benchmark.group = f"chunk growth, {what} + backward, street_a 240x144"
    views = trainer.train_views[::12][:4]

    def render():
        for v in views:
            trainer.render_view(v).color.sum().backward()
            trainer.optimizer.zero_grad(set_to_none=True)

    def hard():
        for v in views[:2]:
            trainer.render_hard_depth(v).sum().backward()
            trainer.optimizer.zero_grad(set_to_none=True)

    benchmark.pedantic(render if what == "render" else hard, rounds=7, warmup_rounds=1)


@pytest.mark.parametrize("path", ["colour only", "two renders, stride 2", "two renders, stride 1", "fused"])
def test_hard_depth_fused(benchmark, trainer, path):
    """The step's render with the hard depth: composited in the same pass (``hard_depth=True``,
    ``TrainConfig.geometry.hard_fused``: every pixel) against a second render (the default: stride 2, or
    every pixel), and the colour render alone (a step without the hard loss); forward and
    backward of 4 training views (every 12th), 240x144."""
    benchmark.group = "hard depth: fused pass vs second render, + backward, street_a 240x144"
    views = trainer.train_views[::12][:4]

    def run():
        for v in views:
            out = trainer.render_view(v, hard_depth=path == "fused")
            loss = out.color.sum() + out.raster.depth.sum()
            if path == "fused":
                loss = loss + out.raster.hard_depth.sum()
            elif path != "colour only":
                loss = loss + trainer.render_hard_depth(v, 2 if path.endswith("2") else 1).sum()
            loss.backward()
            trainer.optimizer.zero_grad(set_to_none=True)

    benchmark.pedantic(run, rounds=7, warmup_rounds=1)
