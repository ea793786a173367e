"""Size of a VAD-GS checkpoint written just before an event, against the same checkpoint without
the VAD-GS state (a baseline checkpoint at the same number of Gaussians), issue 32.

Trains the scene with a TrainConfig JSON and default VAD-GS up to ``--steps`` (448: one step before
street_a's first event, when the loop's renders of every training view are kept), stops, saves,
and prints both sizes and their ratio::

    OMP_NUM_THREADS=1 python benchmarks/checkpoint_size.py ../shared/data/street_a \\
        --config benchmarks/street_config.json --steps 448 --out runs/checkpoint_size
"""

from __future__ import annotations

import argparse
import dataclasses
import json
from pathlib import Path

import torch

from vadgs.data import load_scene
from vadgs.train.checkpoint import CHECKPOINT_NAME, load_checkpoint, save_checkpoint
from vadgs.train.config import TrainConfig
from vadgs.train.trainer import Trainer
from vadgs.train.vad import VisibilityDensifyConfig
from vadgs.train.vad.state import unpack_state


def main() -> None:
    """Command line."""
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("scene")
    ap.add_argument("--config", help="TrainConfig JSON")
    ap.add_argument("--scale", type=float, default=0.5)
    ap.add_argument("--steps", type=int, default=448, help="stop after this step (0-based)")
    ap.add_argument("--out", default="runs/checkpoint_size")
    args = ap.parse_args()
    torch.set_num_threads(1)
    config = TrainConfig.from_dict(json.loads(Path(args.config).read_text())) if args.config else None
    config = dataclasses.replace(config or TrainConfig(), vad=VisibilityDensifyConfig())
    out = Path(args.out)

    def stop(trainer: Trainer, step: int) -> None:
        if step == args.steps:
            trainer.request_stop()

    scene = load_scene(args.scene, scale=args.scale)
    trainer = Trainer(scene, config, out_dir=out, progress=False, callback=stop)
    trainer.train()
    ckpt = load_checkpoint(out)
    size = (out / CHECKPOINT_NAME).stat().st_size
    base = {k: v for k, v in ckpt.strategy_state.items() if not k.startswith(("vad_", "pending"))}
    size_base = save_checkpoint(ckpt._replace(strategy_state=base), out / "baseline_state.pt").stat().st_size
    renders = unpack_state(ckpt.strategy_state).get("vad_renders", {})
    print(
        f"step {trainer.step}: {trainer.model.num_gaussians} Gaussians, {len(renders)} views' renders kept; "
        f"checkpoint {size / 1e6:.2f} MB, without the VAD-GS state {size_base / 1e6:.2f} MB: "
        f"{size / size_base:.3f}x"
    )


if __name__ == "__main__":
    main()
