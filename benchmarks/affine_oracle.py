"""How much of a run's held-out error a colour transform could remove at best (an oracle bound).

For each test view, the affine colour transform ``M rgb + b`` that best maps the run's render to
the ground truth (least squares over the view's pixels, fitted *on the test image itself*) is
applied, and the mean PSNR before and after is printed. No appearance model trained on the
training views can beat a per-view fit on the test image, so the gain bounds what per-camera
appearance (``vadgs train --appearance``) can bring; ``docs/results.md`` (DGP scene_02) uses it.

Run (from the repository root), e.g. on the baseline runs of ``docs/results.md``:

    python benchmarks/affine_oracle.py /work/runs/issue13_app/dgp_base_300 --threads 1
"""

from __future__ import annotations

import argparse
import json

import torch
from kornia.metrics import psnr

from vadgs.train.results.evaluate import render_test_view
from vadgs.train.run import load_run


def best_affine(render: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """``render`` ``(3, H, W)`` after the least-squares affine colour fit to ``target``."""
    x = torch.cat([render.reshape(3, -1).T, torch.ones(render[0].numel(), 1, dtype=render.dtype)], 1)
    w = torch.linalg.lstsq(x, target.reshape(3, -1).T).solution
    return (x @ w).T.reshape_as(target)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("run", help="run folder (or its checkpoint.pt)")
    p.add_argument("--threads", type=int, default=1)
    args = p.parse_args()
    torch.set_num_threads(args.threads)
    run = load_run(args.run)
    model, scene, config = run.model, run.scene, run.config
    raw, fitted = [], []
    for v in scene.test_views:
        render = render_test_view(model, scene, v, config.raster).color.clamp(0, 1)[0]
        gt = scene.load_images([v])[0]
        raw.append(float(psnr(render[None], gt[None], 1.0)))
        fitted.append(float(psnr(best_affine(render, gt).clamp(0, 1)[None], gt[None], 1.0)))
    out = {"psnr": round(sum(raw) / len(raw), 3), "psnr_oracle_affine": round(sum(fitted) / len(fitted), 3)}
    print(json.dumps(out))


if __name__ == "__main__":
    main()
