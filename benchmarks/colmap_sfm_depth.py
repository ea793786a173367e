"""Rendered depth of a COLMAP run against its SfM points, in the held-out views (sparse geometry check).

A COLMAP scene has no ground-truth depth. Its TRACK table says which SfM points each held-out
image observed and where; this script renders every test view of a run and compares the rendered
depth at each observation's pixel with the depth of the observed point in that camera:
``|d_render - d_sfm| / d_sfm`` (AbsRel; median and share below 5 %). The SfM points are
triangulated with the test images too, so this measures the geometry, not novel-view accuracy.

Run (from the repository root):

    python benchmarks/colmap_sfm_depth.py runs/sceaux_baseline runs/sceaux_vadgs
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import torch

from vadgs.geometry import project_points
from vadgs.train.results.evaluate import render_test_view
from vadgs.train.run import load_run


def sfm_depth_errors(run: Path) -> dict:
    """Median AbsRel and share within 5 % of the rendered depth at the test views' SfM observations."""
    loaded = load_run(run)
    model, scene, raster = loaded.model, loaded.scene, loaded.config.raster
    sfm = scene.sfm_points
    out, all_rel = {"per_view": []}, []
    for v in scene.test_views:
        sel = sfm.view_idx == v
        cams = scene.cameras([v])
        _, z = project_points(sfm.points[sfm.point_idx[sel]][None], cams.K, cams.world_to_cam)
        depth = render_test_view(model, scene, v, raster).raster.depth[0, 0]
        h, w = depth.shape
        uv = sfm.uv[sel].round().long()
        ok = (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h) & (z[0] > 0)
        d = depth[uv[ok, 1], uv[ok, 0]]
        rel = ((d - z[0][ok]).abs() / z[0][ok]).where(d > 0, torch.ones_like(d))  # no depth: error 1
        all_rel.append(rel)
        out["per_view"].append(
            {"view": v, "observations": int(ok.sum()), "absrel_median": round(float(rel.median()), 4),
             "within_5pct": round(float((rel < 0.05).float().mean()), 4)}
        )  # fmt: skip
    rel = torch.cat(all_rel)
    out.update(observations=int(rel.numel()), absrel_median=round(float(rel.median()), 4),
               within_5pct=round(float((rel < 0.05).float().mean()), 4))  # fmt: skip
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("runs", nargs="+", type=Path)
    args = p.parse_args()
    torch.set_num_threads(1)
    for run in args.runs:
        res = sfm_depth_errors(run)
        (run / "sfm_depth.json").write_text(json.dumps(res, indent=2))
        print(run, json.dumps({k: v for k, v in res.items()}))


if __name__ == "__main__":
    main()
