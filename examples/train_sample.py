"""Train the baseline on the bundled sample scene with the Python API, then evaluate and export.

Run: ``python examples/train_sample.py [--iterations 100] [--out runs/example]``
(the same as ``vadgs demo`` but spelled out, to show where a custom strategy or loss plugs in).
"""

from __future__ import annotations

import argparse
import json

import torch

from vadgs.data import load_scene, sample_scene_path
from vadgs.train import DefaultStrategy, DefaultStrategyConfig, InitConfig, TrainConfig, Trainer, evaluate
from vadgs.train.results.export import export_model


def main() -> None:
    p = argparse.ArgumentParser()
    p.add_argument("--iterations", type=int, default=100)
    p.add_argument("--out", default="runs/example")
    args = p.parse_args()
    torch.set_num_threads(2)

    scene = load_scene(sample_scene_path(), scale=0.5)
    config = TrainConfig(
        iterations=args.iterations,
        init=InitConfig(voxel_size=0.2, max_points=12_000, sh_degree=1),
        strategy=DefaultStrategyConfig(
            refine_start_iter=40, refine_every=30, reset_every=0, max_gaussians=25_000
        ),
        sh_degree_interval=50,
    )
    strategy = DefaultStrategy(config.strategy)  # the visibility-aware strategy plugs in here

    def extra_losses(step, render, view):  # a loss hook: e.g. keep the sky darker than 1
        return {"sky_reg": 1e-3 * render.sky.clamp(min=1.0).sub(1.0).mean()}

    ref = {"kind": "benchmark", "path": str(sample_scene_path()), "scale": 0.5}
    trainer = Trainer(
        scene, config, out_dir=args.out, scene_ref=ref, strategy=strategy, extra_losses=extra_losses
    )
    result = trainer.train()
    metrics = evaluate(trainer.model, scene).to_dict()
    metrics.pop("per_view")
    print(result)
    print(json.dumps(metrics, indent=2))
    export_model(trainer.model, f"{args.out}/ply", [f.index for f in scene.frames])


if __name__ == "__main__":
    main()
