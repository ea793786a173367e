"""Figure: the same test view rendered by the baseline and by VAD-GS, plus the sign's MVS points.

Top rows: for each run, the render, the rendered depth and normals of the test view where the
traffic sign covers the most pixels, with the sign's box (from the instance map) drawn in red.
Bottom: the sign reconstructed by the VAD-GS pipeline on the final VAD-GS model (best training
reference, diversity-selected views, PatchMatch from the rendered priors, consistency filter)
seen from the side, over the ground-truth sign surface; and the static Gaussian centres of both
runs near the sign.

Run (after ``benchmarks/vad_ablation.py``; ``../shared`` present):

    python benchmarks/vad_figure.py ../shared/data/street_a \
        --baseline runs/ablation_street_a/baseline/checkpoint.pt \
        --vadgs runs/v3_street_a/vadgs/checkpoint.pt --out docs/img/vad_street_a.png
"""

from __future__ import annotations

import argparse
from pathlib import Path

import torch
from vad_ablation import sign_surface  # this folder: run as a script

from vadgs.data import load_scene
from vadgs.geometry import backproject_depth
from vadgs.train.results.evaluate import render_test_view
from vadgs.train.trainer import Trainer
from vadgs.train.vad import VisibilityDensifyConfig, build_visibility_index
from vadgs.train.vad.reconstruct import reconstruct_instance
from vadgs.viz import colorize_depth, image_to_uint8


def _sign_view(scene, sign: int, board_z: float = 4.5) -> tuple[int, tuple[int, int, int, int]]:
    """Test view showing the most of the sign's board (above ``board_z``) and the sign's box there."""
    views = scene.test_views
    ins = scene.load_instances(views)
    cams = scene.cameras(views)
    world = backproject_depth(scene.load_depths(views), cams.K, cams.cam_to_world)  # (B, 3, H, W)
    counts = ((ins == sign) & (world[:, 2] > board_z)).flatten(1).sum(1)
    k = int(counts.argmax())
    ys, xs = torch.nonzero(ins[k] == sign, as_tuple=True)
    return scene.test_views[k], (int(xs.min()), int(ys.min()), int(xs.max()), int(ys.max()))


def main() -> None:
    """Command line."""
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("scene")
    ap.add_argument("--baseline", required=True)
    ap.add_argument("--vadgs", required=True)
    ap.add_argument("--scale", type=float, default=0.5)
    ap.add_argument("--out", default="docs/img/vad_figure.png")
    ap.add_argument("--threads", type=int, default=1)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.patches as patches
    import matplotlib.pyplot as plt

    scene = load_scene(args.scene, scale=args.scale)
    sign = scene.instance_ids("sign")[0]
    view, (x0, y0, x1, y1) = _sign_view(scene, sign)
    runs = {
        "baseline": Trainer.from_checkpoint(args.baseline, scene=scene, progress=False),
        "VAD-GS": Trainer.from_checkpoint(args.vadgs, scene=scene, progress=False),
    }
    gt_depth = scene.load_depths([view])[0, 0]
    vmax = float(gt_depth[gt_depth > 0].quantile(0.98))

    fig = plt.figure(figsize=(13, 10))
    grid = fig.add_gridspec(3, 3, height_ratios=[1, 1, 1.25])
    for r, (name, tr) in enumerate(runs.items()):
        with torch.no_grad():
            out = render_test_view(tr.model, scene, view)
        normals = (-out.raster.normals[0] * 0.5 + 0.5) * (out.raster.normals[0].abs().sum(0) > 0)
        panels = [
            (image_to_uint8(out.color.clamp(0, 1)[0]), f"{name}: render"),
            (colorize_depth(out.raster.depth[0, 0], None, vmax), f"{name}: depth"),
            (image_to_uint8(normals), f"{name}: normals"),
        ]
        for c, (img, title) in enumerate(panels):
            ax = fig.add_subplot(grid[r, c])
            ax.imshow(img)
            ax.add_patch(
                patches.Rectangle((x0 - 2, y0 - 2), x1 - x0 + 4, y1 - y0 + 4, fill=False, ec="red", lw=1.5)
            )
            ax.set_title(title, fontsize=9)
            ax.axis("off")

    # the sign's MVS points on the final VAD-GS model, and the Gaussian centres near the sign
    tr = runs["VAD-GS"]
    index = build_visibility_index(scene)
    train_ins = scene.load_instances(scene.train_views)
    ref = scene.train_views[int((train_ins == sign).flatten(1).sum(1).argmax())]

    def prior(v: int):
        with torch.no_grad():
            o = tr.render_view(v)
        return o.raster.depth[0], o.raster.normals[0]

    rec = reconstruct_instance(index, ref, sign, VisibilityDensifyConfig().reconstruct, None, prior)
    gt = sign_surface(scene, 4000)
    lo, hi = gt.min(0) - 0.5, gt.max(0) + 0.5
    ax = fig.add_subplot(grid[2, 0:2])
    ax.scatter(gt[:, 1], gt[:, 2], s=1, c="0.75", label="ground-truth sign surface")
    pts = rec.points.numpy()
    ax.scatter(pts[:, 1], pts[:, 2], s=3, c=rec.colors.clamp(0, 1).numpy(), label=f"MVS points ({len(pts)})")
    ax.set_xlabel("world y (m)")
    ax.set_ylabel("world z (m)")
    ax.set_aspect("equal")
    ax.set_title(
        f"sign {sign}: fused MVS points from reference view {ref} + views {rec.views[1:]} ({rec.reason})"
    )
    ax.legend(loc="lower left", fontsize=8, markerscale=4)
    ax = fig.add_subplot(grid[2, 2])
    for name, colour in (("baseline", "tab:blue"), ("VAD-GS", "tab:red")):
        g = runs[name].model.gaussians_at(0)
        static = runs[name].model.node_ids[g.ids] == -1
        c = g.means.detach()[static].numpy()
        near = ((c > lo) & (c < hi)).all(1)
        ax.scatter(c[near, 1], c[near, 2], s=1, c=colour, alpha=0.5, label=f"{name} ({int(near.sum())})")
    ax.set_aspect("equal")
    ax.set_xlabel("world y (m)")
    ax.set_title("Gaussian centres around the sign", fontsize=9)
    ax.legend(fontsize=8, markerscale=6)
    fig.suptitle(
        f"{scene.name}: test view {view} ({scene.views[view].camera}, frame {scene.views[view].frame})"
    )
    fig.tight_layout()
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.out, dpi=80)
    print(args.out)


if __name__ == "__main__":
    main()
