"""A converted scene with a sparser LiDAR: the training frames' sweeps thinned, the test frames' kept.

The paper finds VAD-GS's completion "less critical for the Waymo Open dataset, which provides
high-quality point clouds", and "essential for the nuScenes dataset due to its significantly
sparser LiDAR observations". PandaSet's Pandar64 is of the first kind (~100,000 points a sweep);
nuScenes' 32-beam LiDAR returns ~34,000. This writes a copy of a converted scene (``vadgs convert``
output: ``scene.json``, ``lidar/*.npz``) in which each training frame's sweep keeps a random
``--keep`` fraction of its points (the same points whatever the machine: one generator seeded by
``--seed`` and the frame's index), so that the same real images can be trained from a sparse
LiDAR. The test frames' sweeps stay whole: the depth evaluation (``depth.lidar``) measures
against the full held-out sweep (copied). The other folders (images, instance maps, ``gt/``) are
hard-linked, not copied; the top-level files (``scene.json``) are copied. Used for issue 47
(docs/results.md, "A real log")::

    python benchmarks/thin_lidar.py scenes/ps002-36 scenes/ps002-36-sparse --keep 0.25
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
from pathlib import Path

import numpy as np
import torch

from vadgs.data.export import write_lidar_npz
from vadgs.data.scene import read_lidar_npz


def thin_scene(src: Path, out: Path, keep: float, seed: int = 0) -> dict[str, int]:
    """Write ``out``: ``src`` with each training frame's sweep thinned to ``keep`` of its points.

    Returns the points before and after, summed over the thinned sweeps.
    """
    if not 0.0 < keep <= 1.0:
        raise ValueError(f"keep: expected a fraction in (0, 1], got {keep}")
    meta = json.loads((src / "scene.json").read_text())
    if out.exists():
        raise FileExistsError(f"out: {out} exists; choose a new folder (nothing was written)")
    test = set(meta.get("split", {}).get("test_frames", []))
    out.mkdir(parents=True)
    for entry in src.iterdir():  # images, instance maps, ground truth: linked as they are
        if entry.name == "lidar":
            continue
        if entry.is_dir():
            shutil.copytree(entry, out / entry.name, copy_function=os.link)
        else:
            shutil.copy2(entry, out / entry.name)
    before = after = 0
    for frame in meta["frames"]:
        rel = frame.get("lidar")
        if not rel:
            continue
        if frame["index"] in test:
            (out / rel).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(src / rel, out / rel)
            continue
        sweep = read_lidar_npz(src / rel)
        n = len(sweep.points)
        rng = np.random.default_rng([seed, int(frame["index"])])
        kept = torch.from_numpy(np.sort(rng.choice(n, size=max(1, round(keep * n)), replace=False)))
        write_lidar_npz(out / rel, sweep._replace(points=sweep.points[kept], instance=sweep.instance[kept]))
        before += n
        after += len(kept)
    return {"points_before": before, "points_after": after}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("scene", type=Path, help="a converted scene folder (scene.json, lidar/)")
    ap.add_argument("out", type=Path, help="the new scene folder (must not exist)")
    ap.add_argument("--keep", type=float, default=0.25, help="fraction of each training sweep kept")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    counts = thin_scene(args.scene, args.out, args.keep, args.seed)
    print(f"{args.out}: training sweeps {counts['points_before']:,} -> {counts['points_after']:,} points")


if __name__ == "__main__":
    main()
