"""Where PSNR* differs between two checkpoints: the squared error on each track's pixels, per test view.

PSNR* pools the squared error over the moving objects' pixels of the test views; this splits it by
(track, view) and prints the pieces that grew most from the first checkpoint to the second, then the
growth by track. Used for issue 47 on PandaSet 002 (docs/results.md, "A real log")::

    OMP_NUM_THREADS=1 python benchmarks/track_errors.py scenes/ps002 --scale 0.5 \\
        runs/ps002-s0-base.snaps/s500/checkpoint.pt runs/ps002-s0-vad.snaps/s500/checkpoint.pt
"""

from __future__ import annotations

import argparse
import math
import warnings
from collections import defaultdict

import torch

from vadgs.data import load_scene
from vadgs.train.appearance import correct_view
from vadgs.train.results.evaluate import render_test_view
from vadgs.train.trainer import Trainer


def track_errors(scene, checkpoint: str) -> dict[tuple[int, str, int], list[float]]:
    """``(track, camera, frame) -> [sum of squared error, pixels]`` over the test views."""
    tr = Trainer.from_checkpoint(checkpoint, scene, out_dir=None, progress=False)
    out: dict[tuple[int, str, int], list[float]] = defaultdict(lambda: [0.0, 0])
    for v in scene.test_views:
        render = render_test_view(tr.model, scene, v)
        pred = correct_view(tr.appearance, scene, v, render.color).clamp(0, 1).cpu()
        se = ((pred - scene.load_images([v])) ** 2).mean(1)[0]
        inst = scene.load_instances([v])[0]
        for i in inst.unique().tolist():
            if i in scene.tracks:
                m = inst == i
                key = (i, scene.views[v].camera.removesuffix("_camera"), scene.views[v].frame)
                out[key][0] += float(se[m].sum())
                out[key][1] += int(m.sum())
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("scene")
    ap.add_argument("first", help="checkpoint (e.g. the baseline's)")
    ap.add_argument("second", help="checkpoint (e.g. VAD-GS's)")
    ap.add_argument("--scale", type=float, default=0.5)
    ap.add_argument("--top", type=int, default=10)
    args = ap.parse_args()
    torch.set_num_threads(1)
    warnings.simplefilter("ignore")
    scene = load_scene(args.scene, scale=args.scale)
    a, b = track_errors(scene, args.first), track_errors(scene, args.second)
    for name, e in (("first", a), ("second", b)):
        se, n = sum(x[0] for x in e.values()), sum(x[1] for x in e.values())
        print(
            f"{name}: PSNR* {10 * math.log10(n / se):.2f} dB over {n} track pixels"
            if se
            else f"{name}: no track pixel"
        )
    rows = sorted(((b[k][0] - a[k][0], k) for k in a if a[k][1]), reverse=True)
    for grow, (track, cam, frame) in rows[: args.top]:
        n, sa, sb = a[(track, cam, frame)][1], a[(track, cam, frame)][0], b[(track, cam, frame)][0]
        print(
            f"  track {track} ({scene.tracks[track].class_name}) {cam} f{frame}: {n} px, "
            f"{10 * math.log10(n / sa):.2f} -> {10 * math.log10(n / sb):.2f} dB (squared error +{grow:.1f})"
        )
    by: dict[int, float] = defaultdict(float)
    for grow, (track, _, _) in rows:
        by[track] += grow
    print(
        "  growth by track:", ", ".join(f"{t}: {g:+.1f}" for t, g in sorted(by.items(), key=lambda x: -x[1]))
    )


if __name__ == "__main__":
    main()
