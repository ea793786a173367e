"""The ``vadgs`` command line.

Subcommands are registered in :data:`COMMANDS`; each is a function ``(argparse.Namespace) -> int``
with an ``add_arguments(parser)`` attribute. ``vadgs --help`` lists them.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Callable
from pathlib import Path

import torch

__all__ = ["COMMANDS", "main", "visibility"]


def _scene_arg(value: str | None) -> Path:
    from vadgs.data import sample_scene_path

    return Path(value) if value else sample_scene_path()


def visibility(args: argparse.Namespace) -> int:
    """Voxel visibility reasoning on a scene: voxelise LiDAR, z-buffer one view, write a PNG panel."""
    from vadgs.data import load_scene
    from vadgs.data.lidar import accumulate_lidar
    from vadgs.geometry import ZBufferConfig, rasterize_voxels, voxelize
    from vadgs.viz import colorize_depth, colorize_index, image_to_uint8, save_panel

    scene = load_scene(_scene_arg(args.scene), scale=args.scale)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    acc = accumulate_lidar(scene)
    grid = voxelize(acc.points, args.voxel_size, acc.point_views, scene.num_views)
    t1 = time.perf_counter()
    view = args.view if args.view is not None else scene.train_views[len(scene.train_views) // 2]
    raster = rasterize_voxels(
        grid, scene.cameras([view]), [view], ZBufferConfig(only_observed=args.only_observed)
    )
    t2 = time.perf_counter()
    image = scene.load_images([view])[0]
    gt = scene.load_depths([view])[0, 0] if scene.views[view].depth is not None else None
    depth = raster.depth[0, 0]
    panels = [image_to_uint8(image), colorize_depth(depth), colorize_index(raster.index[0])]
    titles = ["image", f"voxel depth ({args.voxel_size} m voxels)", "pixel -> voxel index"]
    metrics = {
        "scene": scene.name,
        "view": view,
        "camera": scene.views[view].camera,
        "frame": scene.views[view].frame,
        "lidar_points": int(acc.points.shape[0]),
        "voxels": len(grid),
        "voxel_view_pairs": int(grid.vis_views.numel()),
        "visible_voxels_in_view": int(raster.visible[0].numel()),
        "voxelize_s": round(t1 - t0, 3),
        "zbuffer_s": round(t2 - t1, 3),
    }
    if gt is not None:
        panels.append(colorize_depth(gt))
        titles.append("ground-truth depth")
        both = (gt > 0) & (depth > 0)
        metrics["gt_pixels_covered"] = round(float(both.sum() / (gt > 0).sum().clamp(min=1)), 4)
        metrics["within_one_voxel"] = round(
            float(((depth - gt).abs()[both] < args.voxel_size).float().mean()) if both.any() else 0.0, 4
        )
    png = save_panel(panels, titles, out / f"visibility_view{view:03d}.png", columns=2)
    (out / "visibility.json").write_text(json.dumps(metrics, indent=2))
    print(json.dumps(metrics, indent=2))
    print(f"wrote {png}")
    return 0


def _visibility_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("scene", nargs="?", help="scene folder (default: the bundled sample)")
    p.add_argument("--out", default="outputs/visibility", help="output folder")
    p.add_argument("--view", type=int, default=None, help="view index (default: a middle training view)")
    p.add_argument("--voxel-size", type=float, default=0.2)
    p.add_argument("--scale", type=float, default=1.0, help="image resolution factor")
    p.add_argument("--only-observed", action="store_true", help="rasterise only voxels observed by the view")


visibility.add_arguments = _visibility_args  # type: ignore[attr-defined]

COMMANDS: dict[str, Callable[[argparse.Namespace], int]] = {"visibility": visibility}


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``vadgs`` console script."""
    parser = argparse.ArgumentParser(
        prog="vadgs", description="VAD-GS: visibility-aware densification for 3DGS"
    )
    parser.add_argument("--threads", type=int, default=None, help="torch CPU threads")
    sub = parser.add_subparsers(dest="command", required=True)
    for name, fn in COMMANDS.items():
        p = sub.add_parser(name, help=(fn.__doc__ or "").strip().splitlines()[0])
        fn.add_arguments(p)  # type: ignore[attr-defined]
    args = parser.parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
    try:
        return COMMANDS[args.command](args)
    except (FileNotFoundError, ValueError) as e:
        print(f"vadgs {args.command}: error: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    raise SystemExit(main())
