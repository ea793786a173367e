"""How the first VAD-GS event of a scene ends, instance by instance, with and without a setting.

Trains one sampling cycle of ``SCENE`` (every training view once, VAD-GS attached, no work budget),
copies the trainer, and runs the event on both copies: the ``ReconstructConfig`` as it is and with
``--off`` (a boolean field) set to False. Prints each event's flagged / attempted / repaired
instances, the Gaussians added and its ``outcomes`` (the (instance, reference) reconstructions by
reason). Used for issue 47 on a converted PandaSet log (docs/results.md, "A real log")::

    vadgs convert pandaset /data/pandaset/002 --frames 0:36 \\
        --cameras front_left_camera,front_camera,front_right_camera --scale 0.25 --out scenes/ps002
    OMP_NUM_THREADS=1 python benchmarks/event_outcomes.py scenes/ps002 --scale 0.5 --off seen_supports
"""

from __future__ import annotations

import argparse
import copy
import dataclasses
import time
import warnings

import torch

from vadgs.data import load_scene
from vadgs.train.config import TrainConfig, scale_schedule
from vadgs.train.trainer import Trainer
from vadgs.train.vad import VisibilityDensifyConfig


def main() -> None:
    """Train one cycle, then run the event with the setting on and off."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scene", help="a scene folder (scene.json)")
    ap.add_argument("--scale", type=float, default=0.5)
    ap.add_argument("--off", default="seen_supports", help="a boolean ReconstructConfig field")
    args = ap.parse_args()
    torch.set_num_threads(1)
    warnings.simplefilter("ignore", UserWarning)
    scene = load_scene(args.scene, scale=args.scale)
    n = len(scene.train_views)
    vad = VisibilityDensifyConfig(every_cycles=1, work_budget=None)
    cfg = scale_schedule(TrainConfig(iterations=3 * n, checkpoint_every=10**6, vad=vad))
    t0 = time.perf_counter()
    on = Trainer(scene, cfg, progress=False)
    print(f"{n} training views, {on.model.num_gaussians} Gaussians at the start", flush=True)
    for _ in range(n - 1):
        on.train_step()
    print(f"{n - 1} steps in {time.perf_counter() - t0:.0f} s", flush=True)
    off = copy.deepcopy(on)
    off.strategy.reconstruct = dataclasses.replace(off.strategy.reconstruct, **{args.off: False})
    for name, trainer in ((f"{args.off}=False", off), (f"{args.off}=True", on)):
        t1 = time.perf_counter()
        trainer.train_step()  # the event's step
        e = trainer.state["vad_events"][-1]
        print(
            f"{name}: {e['flagged_instances']} flagged, {e['attempted']} attempted, {e['repaired']} repaired,"
            f" +{e['added']} Gaussians, {time.perf_counter() - t1:.0f} s\n  outcomes {e['outcomes']}",
            flush=True,
        )


if __name__ == "__main__":
    main()
