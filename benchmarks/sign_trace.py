"""Trace the traffic sign's completeness through a VAD-GS training run.

Trains street_a (or another scene with a sign and ``gt/static.ply``) with the visibility-aware
strategy and, every ``--every`` steps and right after each event, prints one JSON line: the
Gaussian count, the sign's completeness (share of its true surface within 10 cm of a static
Gaussian centre; "board": above 4.5 m), the Gaussians within 10 cm of the sign and their mean
opacity, and how many of those were added by events (the model's ``provenance``, which follows clone,
split and prune). It tells whether a low completeness comes from the reconstruction at the event
or from the added Gaussians not surviving training. Writes ``trace.json`` next to the run.

Run (from the repository root; ../shared present; ~25 min on one CPU thread):

    python benchmarks/sign_trace.py ../shared/data/street_a --config benchmarks/street_config.json \
        --out runs/trace_street_a [--variant no_upsample_no_planar]

The run folder holds a checkpoint: ``vad_ablation.py --out <parent> --variants <variant>`` with the
folder named after the variant evaluates it like its own runs.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
from pathlib import Path

import torch
from scipy.spatial import cKDTree
from vad_ablation import VARIANTS, sign_surface, surface_completeness

from vadgs.data import load_scene
from vadgs.train.config import TrainConfig
from vadgs.train.trainer import Trainer
from vadgs.train.vad import VisibilityAwareDensification


class TracedStrategy(VisibilityAwareDensification):
    """The strategy, tracing the sign's completeness and the Gaussians events added near it.

    A benchmark's subclass: it holds the model (``self.model``, set after the trainer is built) to
    measure completeness; the library's strategy sees only ``params``.
    """

    def __init__(self, surface, every: int, *args, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self.surface, self.every = surface, every
        self.tree = cKDTree(surface)
        self.trace: list[dict] = []
        self.model = None

    def step_post_backward(self, params, optimizers, state, step, info) -> None:
        events = len(state["vad_events"])
        super().step_post_backward(params, optimizers, state, step, info)
        model = self.model
        event = len(state["vad_events"]) > events
        if step % self.every and not event:
            return
        g = model.gaussians_at(0)
        static = model.node_ids[g.ids] == -1
        centres = g.means.detach()[static].numpy()
        opacity = g.opacities.detach()[static]
        tag = model.provenance[g.ids][static]  # the event that added each Gaussian (0: none)
        c = surface_completeness(centres, self.surface)
        near = torch.from_numpy(self.tree.query(centres)[0] < 0.1)
        row = {
            "step": step,
            "event": event,
            "gaussians": model.num_gaussians,
            "completeness": round(c["sign"], 4),
            "board": round(c["sign_board"], 4),
            "near_sign": int(near.sum()),
            "near_sign_opacity": round(float(opacity[near].mean()), 3) if near.any() else None,
            "near_sign_added": int((near & (tag > 0)).sum()),
        }
        if event:
            e = state["vad_events"][-1]
            signs = [i for i in e["instances"] if i["class"] == "sign"]
            row["sign_reconstructed"] = [{"instance": i["instance"], "added": i["added"]} for i in signs]
        self.trace.append(row)
        print(json.dumps(row), flush=True)


def main() -> None:
    """Command line."""
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("scene")
    ap.add_argument("--config", help="TrainConfig JSON")
    ap.add_argument("--scale", type=float, default=0.5)
    ap.add_argument("--out", default="runs/sign_trace")
    ap.add_argument("--every", type=int, default=50)
    ap.add_argument("--threads", type=int, default=1)
    vad = [k for k, v in VARIANTS.items() if v is not None]
    ap.add_argument("--variant", default="vadgs", choices=vad, help="strategy settings (vad_ablation's)")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    scene = load_scene(args.scene, scale=args.scale)
    surface = sign_surface(scene)
    if surface is None:
        raise SystemExit(f"{args.scene}: no sign or no gt/static.ply")
    config = TrainConfig()
    if args.config:
        config = TrainConfig.from_dict(json.loads(Path(args.config).read_text()))
    config = dataclasses.replace(config, vad=VARIANTS[args.variant])
    trainer = Trainer(scene, config, out_dir=args.out, progress=False)  # builds the context and the base
    strategy = TracedStrategy(
        surface, args.every, scene, trainer.strategy_context(), config.vad, base=trainer.strategy.base
    )
    strategy.model = trainer.model
    trainer.strategy = strategy
    trainer.state = strategy.initialize_state(trainer.scene_scale)
    trainer.train()
    (Path(args.out) / "trace.json").write_text(json.dumps(strategy.trace, indent=1))


if __name__ == "__main__":
    main()
