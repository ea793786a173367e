"""The traffic sign reconstructed by the VAD-GS pipeline alone, under several settings.

Loads a trained model (e.g. the baseline's, where the sign is missing), runs the incompleteness
test, picks the sign's reference views as the strategy does and reconstructs it with
:func:`vadgs.train.vad.reconstruct.reconstruct_instance` per setting. Reports the points, their
accuracy (share within 5 cm / 10 cm of the true surface) and the sign's completeness (share of its
true surface within 10 cm of a point; "board": above 4.5 m). No training.

Run (from the repository root; ../shared present):

    python benchmarks/sign_mvs.py ../shared/data/street_a runs/ablation_street_a/baseline/checkpoint.pt
"""

from __future__ import annotations

import argparse
import time
from dataclasses import replace

import numpy as np
import torch
from scipy.spatial import cKDTree
from vad_ablation import sign_surface

from vadgs.data import load_scene
from vadgs.train.trainer import Trainer
from vadgs.train.vad import ReconstructConfig, VisibilityAwareDensification, VisibilityInputs, pick_references
from vadgs.train.vad.reconstruct import reconstruct_instance

SETTINGS = {
    "training resolution": ReconstructConfig(max_upsample=1, planar=None),
    "finer matching (max_upsample=2)": ReconstructConfig(planar=None),
    "finer matching + planar (defaults)": ReconstructConfig(),
    "training resolution, consecutive frames": ReconstructConfig(
        max_upsample=1, planar=None, selection=replace(ReconstructConfig().selection, method="consecutive")
    ),
    "defaults, consecutive frames": ReconstructConfig(
        selection=replace(ReconstructConfig().selection, method="consecutive")
    ),
}


def main() -> None:
    """Command line."""
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("scene")
    ap.add_argument("checkpoint")
    ap.add_argument("--scale", type=float, default=0.5)
    ap.add_argument("--threads", type=int, default=1)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    scene = load_scene(args.scene, scale=args.scale)
    sign = scene.instance_ids("sign")[0]
    surface = sign_surface(scene)
    board = surface[:, 2] > 4.5
    trainer = Trainer.from_checkpoint(args.checkpoint, scene=scene, progress=False)
    strategy = VisibilityAwareDensification()
    strategy.prepare(VisibilityInputs.from_scene(scene), trainer.strategy_context())
    rows, views = strategy.detect()
    hit = torch.nonzero(rows.flagged & (rows.instance == sign)).squeeze(1).tolist()
    flagged = [(views[int(rows.view[k])], int(rows.pixels[k])) for k in hit]
    if not flagged:
        raise SystemExit(f"sign {sign} is not flagged in this model: nothing to reconstruct")
    refs = pick_references(flagged, scene, strategy.config.references, strategy.config.min_frame_gap)
    print(f"sign {sign}: flagged in {len(flagged)} views; references {refs}")

    def prior(v: int):
        out = trainer.render_view(v)
        return out.raster.depth[0].detach(), out.raster.normals[0].detach()

    index = strategy.prepare()
    print("| setting | groups | points | within 5 cm | within 10 cm | sign compl. | board compl. | s |")
    print("|---|---|---|---|---|---|---|---|")
    for name, cfg in SETTINGS.items():
        t0 = time.perf_counter()
        gen = torch.Generator().manual_seed(1)
        recs = [reconstruct_instance(index, r, sign, cfg, gen, prior) for r in refs]
        pts = torch.cat([r.points for r in recs]).numpy()
        groups = "; ".join(str(r.views) for r in recs)
        if not len(pts):
            print(f"| {name} | {groups} | 0 | – | – | – | – | {time.perf_counter() - t0:.0f} |")
            continue
        to_surface = cKDTree(surface).query(pts)[0]
        to_points = cKDTree(pts).query(surface)[0]
        print(
            f"| {name} | {groups} | {len(pts)} | {np.mean(to_surface < 0.05):.2f} | "
            f"{np.mean(to_surface < 0.1):.2f} | {np.mean(to_points < 0.1):.2f} | "
            f"{np.mean(to_points[board] < 0.1):.2f} | {time.perf_counter() - t0:.0f} |"
        )


if __name__ == "__main__":
    main()
