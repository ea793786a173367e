"""Build the small sample scene bundled with vadgs from ../shared/data/street_a.

A cut of street_a: frames 16-23 (the traffic sign and the overtaken car are in view), all three
cameras at half resolution (240x144), LiDAR subsampled to 12k points per frame. The split keeps
the rule of the full scene (every fourth frame held out). Run from the repository root:

    python tools/make_sample_scene.py [--src ../shared/data/street_a] [--dst vadgs/data/sample_scene]
"""

from __future__ import annotations

import argparse
import json
import shutil
from pathlib import Path

import numpy as np
from PIL import Image

FRAMES = list(range(16, 24))
SCALE = 0.5
LIDAR_POINTS = 12000


def main() -> None:
    """Write the sample scene."""
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--src", type=Path, default=Path("../shared/data/street_a"))
    ap.add_argument("--dst", type=Path, default=Path("vadgs/data/sample_scene"))
    args = ap.parse_args()
    meta = json.loads((args.src / "scene.json").read_text())
    if args.dst.exists():
        shutil.rmtree(args.dst)
    rng = np.random.default_rng(0)

    cams = {}
    for name, c in meta["cameras"].items():
        K = np.array(c["K"])
        K[:2, :2] *= SCALE
        K[:2, 2] = (K[:2, 2] + 0.5) * SCALE - 0.5
        cams[name] = dict(c, width=round(c["width"] * SCALE), height=round(c["height"] * SCALE), K=K.tolist())

    frames = []
    for f in meta["frames"]:
        if f["index"] not in FRAMES:
            continue
        for v in f["views"]:
            for key, mode in (("image", Image.BOX), ("instances", Image.NEAREST)):
                im = Image.open(args.src / v[key])
                w, h = im.size
                out = args.dst / v[key]
                out.parent.mkdir(parents=True, exist_ok=True)
                im.resize((round(w * SCALE), round(h * SCALE)), mode).save(out, optimize=True)
            with np.load(args.src / v["depth"]) as z:
                d = z["depth"][::2, ::2] if SCALE == 0.5 else z["depth"]
            out = args.dst / v["depth"]
            out.parent.mkdir(parents=True, exist_ok=True)
            np.savez_compressed(out, depth=d.astype(np.float16))
        with np.load(args.src / f["lidar"]) as z:
            keep = np.sort(
                rng.choice(len(z["points"]), size=min(LIDAR_POINTS, len(z["points"])), replace=False)
            )
            out = args.dst / f["lidar"]
            out.parent.mkdir(parents=True, exist_ok=True)
            np.savez_compressed(
                out, points=z["points"][keep], instance=z["instance"][keep], origin=z["origin"]
            )
        frames.append(f)

    tracks = []
    for t in meta["tracks"]:
        t = dict(t, object_to_world={k: v for k, v in t["object_to_world"].items() if int(k) in FRAMES})
        if t.get("mesh"):
            (args.dst / t["mesh"]).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy(args.src / t["mesh"], args.dst / t["mesh"])
        tracks.append(t)

    test = [i for i in FRAMES if i in meta["split"]["test_frames"]]
    sample = dict(
        meta,
        name="street_a_sample",
        description="street_a frames 16-23, half resolution, LiDAR subsampled (tools/make_sample_scene.py)",
        cameras=cams,
        frames=frames,
        tracks=tracks,
        split=dict(meta["split"], test_frames=test, train_frames=[i for i in FRAMES if i not in test]),
    )
    sample.pop("gt_static_mesh", None)
    (args.dst / "scene.json").write_text(json.dumps(sample, indent=1))
    size = sum(p.stat().st_size for p in args.dst.rglob("*") if p.is_file())
    print(f"wrote {args.dst} ({size / 1e6:.2f} MB)")


if __name__ == "__main__":
    main()
