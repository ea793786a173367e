"""The geometric losses' depth prior of each training view against the view's own LiDAR sweep.

VAD-GS's prior where no MVS depth exists is the voxel depth of the pixel's own instance; for a
moving object, its grid posed at the view's time. Prints, on the tracks' pixels and on the rest,
how much of the prior lies more than 10 % off the sweep, then by track. Used for issue 47 on
PandaSet 002 (docs/results.md, "A real log")::

    OMP_NUM_THREADS=1 python benchmarks/prior_vs_lidar.py scenes/ps002 RUN/checkpoint.pt --scale 0.5
"""

from __future__ import annotations

import argparse
import warnings
from collections import defaultdict

import torch

from vadgs.data import load_scene
from vadgs.data.lidar import lidar_depth_map
from vadgs.train.trainer import Trainer


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("scene")
    ap.add_argument("checkpoint", help="a VAD-GS run's checkpoint")
    ap.add_argument("--scale", type=float, default=0.5)
    args = ap.parse_args()
    torch.set_num_threads(1)
    warnings.simplefilter("ignore")
    scene = load_scene(args.scene, scale=args.scale)
    tr = Trainer.from_checkpoint(args.checkpoint, scene, out_dir=None, progress=False)
    index = tr.strategy.prepare()
    tracks = torch.tensor(sorted(scene.tracks), dtype=torch.long)
    groups: dict[str, list[float]] = defaultdict(lambda: [0, 0, 0.0])  # pixels, > 10 % off, sum AbsRel
    per_track: dict[int, list[int]] = defaultdict(lambda: [0, 0])
    for v in scene.train_views:
        targets = tr.strategy.geometry_targets(tr.state, v)
        if targets is None or targets.depth is None:
            continue
        prior = targets.depth[0, 0].cpu()
        sweep = lidar_depth_map(scene, v)[0, 0]
        inst = index.instances(v)[: prior.shape[0], : prior.shape[1]].cpu()
        both = (prior > 0) & (sweep > 0)
        rel = (prior - sweep).abs() / sweep.clamp_min(1e-6)
        moving = torch.isin(inst, tracks)
        for name, m in (("tracks", both & moving), ("the rest", both & ~moving)):
            g = groups[name]
            g[0] += int(m.sum())
            g[1] += int((rel[m] > 0.1).sum())
            g[2] += float(rel[m].sum())
        for t in inst[both & moving].unique().tolist():
            m = both & (inst == t)
            per_track[t][0] += int(m.sum())
            per_track[t][1] += int((rel[m] > 0.1).sum())
    for name, (n, off, total) in groups.items():
        print(
            f"{name}: {int(n)} pixels with a prior and a return, "
            f"{100 * off / max(n, 1):.1f} % off by > 10 %, mean AbsRel {total / max(n, 1):.3f}"
        )
    for t, (n, off) in sorted(per_track.items(), key=lambda x: -x[1][0])[:10]:
        print(
            f"  track {t} ({scene.tracks[t].class_name}): {n} pixels, "
            f"{100 * off / max(n, 1):.1f} % off by > 10 %"
        )


if __name__ == "__main__":
    main()
