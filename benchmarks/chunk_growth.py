"""The compositor's steps with and without growing chunks, and an interleaved timing of both.

Prints, for the street_a trainer (``benchmarks/street_config.json``, 240x144; view 0): how many
compositing steps a colour render and a hard depth render (opacity 1, ``geometry.hard_stride``) take and
how many of them run with at most 10 tiles active, with the chunk growth on (default) and off
(``_MAX_CHUNK_GROWTH = 1``: the compositor before). Then times forward+backward of renderer cases
1 and 2 (``bench_render.py``) alternating growth off / on in one process (median of the rounds
after the first), which is less sensitive to the machine's drift than two separate benchmark
blocks. Needs ../shared.

    OMP_NUM_THREADS=1 python benchmarks/chunk_growth.py [--rounds 7]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import statistics
import sys
import time
from pathlib import Path

import torch

import vadgs.render.composite as composite
from vadgs.data import load_scene
from vadgs.render import RasterConfig
from vadgs.train.config import TrainConfig
from vadgs.train.trainer import Trainer

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
from bench_render import STREET, _forward_backward, random_scene, street_scene  # noqa: E402


def _steps(render) -> list[int]:
    """Active tiles of each compositing step of ``render()`` (no gradient)."""
    counts: list[int] = []
    gather = composite._gather_chunk

    def spy(s, table, active, start, c):
        counts.append(active.numel())
        return gather(s, table, active, start, c)

    composite._gather_chunk = spy
    try:
        with torch.no_grad():
            render()
    finally:
        composite._gather_chunk = gather
    return counts


def main() -> None:
    """Command line."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rounds", type=int, default=7)
    args = ap.parse_args()
    torch.set_num_threads(1)
    config = TrainConfig.from_dict(json.loads((HERE / "street_config.json").read_text()))
    config = dataclasses.replace(
        config, strategy=dataclasses.replace(config.strategy, refine_start_iter=10**9)
    )
    trainer = Trainer(
        load_scene(STREET, scale=0.5), dataclasses.replace(config, checkpoint_every=0), progress=False
    )
    view = trainer.train_views[0]
    for growth in (1, composite._MAX_CHUNK_GROWTH):
        before, composite._MAX_CHUNK_GROWTH = composite._MAX_CHUNK_GROWTH, growth
        for name, render in (
            ("colour", lambda: trainer.render_view(view)),
            ("hard depth", lambda: trainer.render_hard_depth(view)),
        ):
            c = _steps(render)
            print(f"growth {growth:2d}, {name} render of view {view}: {len(c)} steps, "
                  f"{sum(n <= 10 for n in c)} with <= 10 of {c[0]} tiles active")  # fmt: skip
        composite._MAX_CHUNK_GROWTH = before
    scenes = {"case 1": random_scene(), "case 2": street_scene()}
    times: dict = {}
    growth = composite._MAX_CHUNK_GROWTH
    for _ in range(args.rounds):
        for g in (1, growth):
            composite._MAX_CHUNK_GROWTH = g
            for name, scene in scenes.items():
                t0 = time.perf_counter()
                _forward_backward(scene, RasterConfig())
                times.setdefault((name, g), []).append(time.perf_counter() - t0)
    composite._MAX_CHUNK_GROWTH = growth
    for name in scenes:
        fixed, grown = (statistics.median(times[(name, g)][1:]) * 1000 for g in (1, growth))
        print(f"{name} forward+backward, interleaved: fixed chunks {fixed:.0f} ms, growing {grown:.0f} ms")


if __name__ == "__main__":
    main()
