"""Trained variants on the test views and on the extrapolated (novel) views, side by side.

Loads each variant's checkpoint, evaluates it on the test split and on every group of the scene's
novel views (street_a: the test frames seen again from the rig shifted 2 m left, ``shift+2.0``, and
2 m right, ``shift-2.0``), with the metrics of :mod:`vadgs.train.results.evaluate`: PSNR, SSIM, PSNR*
(moving cars), depth AbsRel and δ<1.05 on all pixels, the traffic sign and facades above 5 m.
Prints two markdown tables (the metrics per view set; the loss from the test views to each shift
and the mean of the shifts) and writes them with the JSON of every variant, and a figure of one
shifted view: the ground truth (image, depth, normals from the depth) and one row per variant
(render, depth, normals).

Checkpoints are ``RUN_DIR/<variant>/checkpoint.pt`` (as ``benchmarks/vad_ablation.py`` writes
them) or given one by one with ``--checkpoint NAME=PATH``. Run (from the repository root;
../shared present), e.g. on the runs of ``docs/results.md``:

    python benchmarks/novel_views.py --scene ../shared/data/street_a --scale 0.5 \
        --checkpoint baseline=runs/ablation_street_a/baseline/checkpoint.pt \
        --checkpoint vadgs=runs/v6_street_a/vadgs/checkpoint.pt \
        --out runs/novel_street_a --figure docs/img/novel_street_a.png

    # or, all variants in one folder
    python benchmarks/novel_views.py runs/ablation_street_a --variants baseline vadgs \
        --scene ../shared/data/street_a --scale 0.5
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from vadgs.data import load_scene
from vadgs.data.scene import Scene
from vadgs.geometry import backproject_depth
from vadgs.render import RasterConfig
from vadgs.train.model import GaussianModel
from vadgs.train.results.evaluate import evaluate_split, render_test_view
from vadgs.train.run import load_run

LABELS = {"baseline": "baseline", "vadgs": "VAD-GS"}
REGIONS = (("all", "all"), ("sign", "sign"), ("upper_facade", "facade>5m"))


def load_variant(path: str | Path) -> tuple[GaussianModel, RasterConfig, int]:
    """The model of a checkpoint, its rasterizer settings and its step."""
    run = load_run(path, open=False)
    return run.model, run.config.raster, run.step


def evaluate_views(model: GaussianModel, scene: Scene, raster: RasterConfig | None = None) -> dict[str, dict]:
    """``{"test": metrics, "<group>": metrics, ...}`` (:class:`EvalMetrics` dicts, no LPIPS)."""
    out = {k: m.to_dict() for k, m in evaluate_split(model, scene, "test", raster, with_lpips=False).items()}
    if scene.novel_views:
        novel = evaluate_split(model, scene, "novel", raster, with_lpips=False)
        out.update({k: m.to_dict() for k, m in novel.items()})
    return out


def _values(m: dict) -> dict[str, float | None]:
    v: dict[str, float | None] = {"PSNR": m["psnr"], "SSIM": m["ssim"], "PSNR*": m["psnr_star"]}
    for region, label in REGIONS:
        d = m["depth"].get(region, {})
        v[f"AbsRel {label}"] = d.get("absrel")
        v[f"δ<1.05 {label}"] = d.get("delta_1.05")
    return v


def _fmt(x: float | None, p: int = 3, sign: bool = False) -> str:
    if x is None or x != x:
        return "–"
    return f"{x:+.{p}f}" if sign else f"{x:.{p}f}"


def _precision(col: str) -> int:
    return 2 if col.startswith("PSNR") else 3


def losses(results: dict[str, dict]) -> dict[str, dict[str, float | None]]:
    """Per novel group (and ``"mean"`` over them): shifted minus test for every metric of the table."""
    test = _values(results["test"])
    out: dict[str, dict[str, float | None]] = {}
    for group, m in results.items():
        if group == "test":
            continue
        v = _values(m)
        out[group] = {k: (v[k] - test[k]) if v[k] is not None and test[k] is not None else None for k in v}
    if out:
        out["mean"] = {}
        for k in test:
            vals = [g[k] for g in out.values() if g and g.get(k) is not None]
            out["mean"][k] = sum(vals) / len(vals) if len(vals) == len(out) - 1 else None
    return out


def tables(all_results: dict[str, dict[str, dict]]) -> str:
    """Two markdown tables: the metrics per variant and view set, and the loss from test to shifted."""
    cols = list(_values(next(iter(next(iter(all_results.values())).values()))))
    rows = ["| variant | views | " + " | ".join(cols) + " |", "|---|---|" + "---|" * len(cols)]
    for name, res in all_results.items():
        for group, m in res.items():
            v = _values(m)
            cells = [LABELS.get(name, name), f"{group} ({m['num_views']})"]
            cells += [_fmt(v[c], _precision(c)) for c in cols]
            rows.append("| " + " | ".join(cells) + " |")
    note = "Change from the test views to the shifted ones (shifted − test; PSNR, SSIM, δ: negative is a loss"
    rows += ["", note + "; AbsRel: positive is a loss):", ""]
    rows += ["| variant | test → | " + " | ".join(cols) + " |", "|---|---|" + "---|" * len(cols)]
    for name, res in all_results.items():
        for group, d in losses(res).items():
            cells = [LABELS.get(name, name), group] + [_fmt(d[c], _precision(c), sign=True) for c in cols]
            rows.append("| " + " | ".join(cells) + " |")
    return "\n".join(rows)


def depth_normals(depth: torch.Tensor, K: torch.Tensor) -> torch.Tensor:
    """Camera-frame normals ``(3, H, W)`` of a depth map ``(H, W)``, central differences (0: unknown)."""
    pts = backproject_depth(depth[None, None], K[None])[0]  # (3, H, W) camera frame
    du = torch.zeros_like(pts)
    dv = torch.zeros_like(pts)
    du[:, :, 1:-1] = pts[:, :, 2:] - pts[:, :, :-2]
    dv[:, 1:-1] = pts[:, 2:] - pts[:, :-2]
    n = F.normalize(torch.linalg.cross(du, dv, dim=0), dim=0)
    n = torch.where((n * pts).sum(0, keepdim=True) > 0, -n, n)  # towards the camera
    ok = depth > 0
    ok[1:-1, 1:-1] &= (
        (depth[2:, 1:-1] > 0) & (depth[:-2, 1:-1] > 0) & (depth[1:-1, 2:] > 0) & (depth[1:-1, :-2] > 0)
    )
    ok[[0, -1]] = False
    ok[:, [0, -1]] = False
    return n * ok


def pick_view(scene: Scene, group: str | None = None) -> int:
    """The novel view (of ``group``, default the first) showing the most traffic-sign pixels."""
    groups = scene.novel_groups()
    if not groups:
        raise ValueError(f"scene {scene.name!r} has no novel views")
    views = groups[group or next(iter(groups))]
    signs = torch.tensor(scene.instance_ids("sign"), dtype=torch.long)
    if not signs.numel() or scene.views[views[0]].instances is None:
        return views[len(views) // 2]
    counts = [int(torch.isin(scene.load_instances([v]), signs).sum()) for v in views]
    return views[int(np.argmax(counts))]


def novel_figure(
    models: dict[str, tuple[GaussianModel, RasterConfig | None]], scene: Scene, view: int, path: str | Path
) -> Path:
    """One view: ground truth (image, depth, its normals), then render, depth, normals per variant."""
    from kornia.metrics import psnr

    from vadgs.viz import colorize_depth, colorize_normals, image_to_uint8, save_panel

    info = scene.views[view]
    gt = scene.load_images([view])[0]
    gtd = scene.load_depths([view])[0, 0]
    vmax = float(gtd[gtd > 0].quantile(0.98))
    vmin = float(gtd[gtd > 0].quantile(0.02))
    K = scene.cameras([view]).K[0]
    where = f"{info.camera}, frame {info.frame}, {info.group or 'test'}"
    images = [image_to_uint8(gt), colorize_depth(gtd, vmin, vmax), colorize_normals(depth_normals(gtd, K))]
    titles = [f"ground truth ({where})", "ground-truth depth", "normals of the ground-truth depth"]
    for name, (model, raster) in models.items():
        out = render_test_view(model, scene, view, raster)
        p = float(psnr(out.color.clamp(0, 1), gt[None], 1.0))
        d = out.raster.depth[0, 0]
        valid = gtd > 0
        absrel = float(((d[valid] - gtd[valid]).abs() / gtd[valid]).mean())
        label = LABELS.get(name, name)
        images += [
            image_to_uint8(out.color[0]),
            colorize_depth(d, vmin, vmax),
            colorize_normals(out.raster.normals[0]),
        ]
        titles += [
            f"{label}: render ({p:.2f} dB)",
            f"{label}: depth (AbsRel {absrel:.3f})",
            f"{label}: normals",
        ]
    return save_panel(images, titles, path, columns=3)


def main(argv: list[str] | None = None) -> int:
    """Command line."""
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument(
        "run_dir", nargs="?", help="folder with one sub-folder per variant (<variant>/checkpoint.pt)"
    )
    ap.add_argument("--variants", nargs="*", default=["baseline", "vadgs"])
    ap.add_argument("--checkpoint", action="append", default=[], help="NAME=PATH (instead of RUN_DIR/NAME)")
    ap.add_argument("--scene", required=True, help="the scene folder (with novel_views)")
    ap.add_argument("--scale", type=float, default=0.5)
    ap.add_argument("--out", help="folder of the JSON and table (default RUN_DIR/novel_views)")
    ap.add_argument(
        "--figure", default="docs/img/novel_street_a.png", help="PNG of one shifted view ('' for none)"
    )
    ap.add_argument("--figure-view", type=int, help="view index of the figure (default: most sign pixels)")
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    paths: dict[str, Path] = {}
    if args.checkpoint:
        for item in args.checkpoint:
            name, sep, path = item.partition("=")
            if not sep:
                ap.error(f"--checkpoint: expected NAME=PATH, got {item!r}")
            paths[name] = Path(path)
    else:
        if not args.run_dir:
            ap.error("give RUN_DIR or --checkpoint NAME=PATH")
        paths = {v: Path(args.run_dir) / v / "checkpoint.pt" for v in args.variants}
    out = Path(args.out) if args.out else Path(args.run_dir or "runs") / "novel_views"
    out.mkdir(parents=True, exist_ok=True)
    scene = load_scene(args.scene, scale=args.scale)
    results, models = {}, {}
    for name, path in paths.items():
        model, raster, step = load_variant(path)
        models[name] = (model, raster)
        results[name] = evaluate_views(model, scene, raster)
        payload = {"checkpoint": str(path), "step": step, "scene": str(args.scene), "scale": args.scale}
        (out / f"{name}.json").write_text(json.dumps(payload | {"views": results[name]}, indent=1))
        print(f"{name}: evaluated on {', '.join(results[name])}", flush=True)
    md = tables(results)
    (out / "table.md").write_text(md + "\n")
    print(md)
    if args.figure and scene.novel_views:
        view = args.figure_view if args.figure_view is not None else pick_view(scene)
        print(f"wrote {novel_figure(models, scene, view, args.figure)} (view {view})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
