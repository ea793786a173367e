"""PatchMatch work of the VAD-GS events of a street run, per instance: what ``work_budget`` needs.

Trains ``STEPS`` steps of a street scene at half resolution with ``benchmarks/street_config.json``
and VAD-GS without a budget (``work_budget=None``: every candidate attempted; otherwise the
defaults), on one thread, then prints each event's work (PatchMatch pixel-sweeps,
:func:`vadgs.train.vad.matching.match_work`) per training pixel so far, and each instance's work
cumulated in ranking order: the ``work_budget`` at which the event would stop after it::

    python benchmarks/event_work.py ../shared/data/street_a --steps 452    # the first event (step 449)
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path

import torch

from vadgs.data import load_scene
from vadgs.train.config import TrainConfig
from vadgs.train.trainer import Trainer
from vadgs.train.vad import VisibilityDensifyConfig


def main() -> None:
    """Train, then print the events' work."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scene", help="a street scene folder")
    ap.add_argument("--steps", type=int, default=452)
    args = ap.parse_args()
    torch.set_num_threads(1)
    cfg = TrainConfig.from_dict(json.loads((Path(__file__).parent / "street_config.json").read_text()))
    vad = VisibilityDensifyConfig(work_budget=None, time_budget=None)
    trainer = Trainer(load_scene(args.scene, scale=0.5), dataclasses.replace(cfg, vad=vad), progress=False)
    t0 = time.perf_counter()
    for _ in range(args.steps):
        trainer.train_step()
    print(f"{args.steps} steps in {time.perf_counter() - t0:.0f} s, {trainer.model.num_gaussians} Gaussians")
    for e in trainer.state["vad_events"]:
        px = trainer.strategy.trained_pixels(e["step"])
        print(
            f"event at step {e['step']}: {e['flagged_instances']} flagged, {e['candidates']} candidates, "
            f"{e['attempted']} attempted, +{e['added']} Gaussians, work {e['work']:.0f} pixel-sweeps = "
            f"{e['work'] / px:.4f} per training pixel ({px:.0f}), {e['total_s']:.1f} s"
        )
        cum = 0.0
        for k, i in enumerate(e["instances"], 1):
            cum += i["work"]
            print(f"  {k:3d} {i['class']:>10} {i['instance']:4d} work {i['work']:9.0f}  cumulated "
                  f"{cum / px:.4f}  +{i['added']}")  # fmt: skip


if __name__ == "__main__":
    main()
