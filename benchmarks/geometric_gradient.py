"""How much of the densification's gradient the geometric losses make, view by view.

The standard densification grows the Gaussians whose projected mean (``means2d``) has a large
gradient, summed over every loss term of the step. This takes a VAD-GS checkpoint and, on its
first views with priors, splits that gradient into the colour side (colour, LiDAR, appearance)
and the geometric side (L_soft, L_normal, and L_hard until 80 % of the run), and counts the
visible Gaussians over the growth threshold (``strategy.grow_grad2d``) with the geometric side
and under it without: the Gaussians a step's geometric terms alone push over. ``--min-share``
sets ``TrainConfig.geometry.min_prior_share`` for the split (default: the checkpoint's). Also
prints how much of each view its priors cover. Used for issue 47 on PandaSet 002 and street_a
(docs/results.md, "A real log")::

    OMP_NUM_THREADS=1 python benchmarks/geometric_gradient.py RUN/checkpoint.pt --min-share 0
    OMP_NUM_THREADS=1 python benchmarks/geometric_gradient.py RUN/checkpoint.pt --min-share 0.1

A single step's gradient, not the average over the steps the strategy keeps: a proxy for what
pushes a Gaussian over the threshold, not a replay of the run.
"""

from __future__ import annotations

import argparse
import dataclasses
import statistics
import tempfile

import torch

from vadgs.train.trainer import Trainer

COLOUR = ("color", "lidar", "appearance")
GEOMETRIC = ("soft", "hard", "normal")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("checkpoint", help="a VAD-GS run's checkpoint.pt (with priors in its strategy state)")
    ap.add_argument("--views", type=int, default=10, help="how many views with priors (the first)")
    ap.add_argument("--min-share", type=float, default=None, help="geometry.min_prior_share for the split")
    args = ap.parse_args()
    torch.set_num_threads(1)
    with tempfile.TemporaryDirectory() as out:  # the trainer's folder: nothing written to the run's
        tr = Trainer.from_checkpoint(args.checkpoint, out_dir=out, progress=False)
        cfg = tr.config
        if args.min_share is not None:
            geometry = dataclasses.replace(cfg.geometry, min_prior_share=args.min_share)
            tr.objective.config = dataclasses.replace(cfg, geometry=geometry)
        priors = tr.state["vad_priors"]
        shares = [float((d > 0).float().mean()) for d, _ in priors.values()]
        print(
            f"step {tr.step}, {tr.model.params['means'].shape[0]} Gaussians, "
            f"min_prior_share {tr.objective.config.geometry.min_prior_share}; {len(priors)} views with "
            f"priors, covering {statistics.median(shares):.2%} of a view (median), "
            f"{sum(s < 0.1 for s in shares)} under 10 %"
        )
        threshold = cfg.strategy.grow_grad2d
        total = {"colour": 0.0, "geometric": 0.0, "pushed": 0, "over": 0}
        for view in sorted(priors)[: args.views]:
            out_ = tr.render_view(view)
            m2 = out_.raster.means2d
            terms = tr.objective(tr.step, view, out_, tr.render_hard_depth)
            colour = torch.stack([t for k, t in terms.items() if k in COLOUR]).sum()
            geo = [t for k, t in terms.items() if k in GEOMETRIC]
            (gc,) = torch.autograd.grad(colour, m2, retain_graph=True)
            gg = torch.autograd.grad(torch.stack(geo).sum(), m2)[0] if geo else torch.zeros_like(gc)
            h, w = out_.color.shape[-2:]
            to_px = torch.tensor([w / 2.0, h / 2.0])  # NDC to pixels, as the strategy measures it
            nc, ng, nt = ((g[0] * to_px).norm(dim=-1) for g in (gc, gg, gc + gg))
            vis = out_.raster.visible[0]
            pushed = int(((nc < threshold) & (nt >= threshold) & vis).sum())
            over = int(((nt >= threshold) & vis).sum())
            px = int((priors[view][0] > 0).sum())
            colour_sum, geo_sum = float(nc[vis].sum()), float(ng[vis].sum())
            print(
                f"view {view}: {px} prior px; "
                + ", ".join(f"{k} {float(t.detach()):.4f}" for k, t in terms.items())
                + f"; gradient colour {colour_sum:.3f} geometric {geo_sum:.3f}; "
                f"over the threshold {over}, pushed over by the geometric terms {pushed}"
            )
            total["colour"] += colour_sum
            total["geometric"] += geo_sum
            total["pushed"] += pushed
            total["over"] += over
        print(
            f"all: geometric / colour gradient {total['geometric'] / total['colour']:.1%}; "
            f"{total['pushed']} of {total['over']} over the threshold pushed there by the geometric terms"
        )


if __name__ == "__main__":
    main()
