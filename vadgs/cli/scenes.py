"""Commands on a scene's data: ``vadgs visibility``, ``vadgs convert``, ``vadgs check``."""

from __future__ import annotations

import argparse
import json
import time

from vadgs.cli._common import _check_out_dir, _int_at_least, _positive_float, _scene_arg
from vadgs.io import write_json


def visibility(args: argparse.Namespace) -> int:
    """Voxel visibility reasoning on a scene: voxelise LiDAR, z-buffer one view, write a PNG panel."""
    from vadgs.data import load_scene
    from vadgs.data.lidar import accumulate_lidar
    from vadgs.geometry import ZBufferConfig, rasterize_voxels, voxelize
    from vadgs.viz import colorize_depth, colorize_index, image_to_uint8, save_panel

    out = _check_out_dir(args.out)
    scene = load_scene(_scene_arg(args.scene), scale=args.scale)
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
    write_json(out / "visibility.json", metrics)
    print(json.dumps(metrics, indent=2))
    print(f"wrote {png}")
    return 0


def _visibility_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("scene", nargs="?", help="scene folder (default: the bundled sample)")
    p.add_argument("--out", default="outputs/visibility", help="output folder")
    p.add_argument(
        "--view", type=_int_at_least(0), default=None, help="view index (default: a middle training view)"
    )
    p.add_argument("--voxel-size", type=_positive_float, default=0.2)
    p.add_argument("--scale", type=_positive_float, default=1.0, help="image resolution factor")
    p.add_argument("--only-observed", action="store_true", help="rasterise only voxels observed by the view")


visibility.add_arguments = _visibility_args  # type: ignore[attr-defined]


def convert(args: argparse.Namespace) -> int:
    """Convert a nuScenes scene or a Waymo v2 segment into the benchmark format (``scene.json``)."""
    from vadgs.data import export_scene, load_nuscenes, load_waymo

    cameras = args.cameras.split(",") if args.cameras else None
    frames = None
    if args.frames:
        start, _, stop = args.frames.partition(":")
        frames = range(int(start or 0), int(stop)) if stop else [int(start)]
    if args.dataset == "nuscenes":
        scene = load_nuscenes(
            args.src, args.scene, version=args.version, cameras=cameras, scale=args.scale, frames=frames
        )
    else:
        lasers = None if args.no_lidar else ("TOP",)  # --no-lidar: a segment without the lidar component
        scene = load_waymo(
            args.src, args.scene, cameras=cameras, scale=args.scale, frames=frames, lasers=lasers
        )
    path = export_scene(scene, args.out, lidar=not args.no_lidar)
    print(f"{scene!r} -> {path}")
    return 0


def _convert_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("dataset", choices=["nuscenes", "waymo"])
    p.add_argument("src", help="nuScenes dataroot, or the Waymo v2 split folder holding the components")
    p.add_argument("--scene", required=True, help="nuScenes scene name (scene-0061) or Waymo segment name")
    p.add_argument("--out", required=True, help="output folder for scene.json, images/, lidar/")
    p.add_argument("--version", default="v1.0-mini", help="nuScenes table folder (v1.0-mini, v1.0-trainval)")
    p.add_argument("--cameras", help="comma-separated camera names (default all)")
    p.add_argument("--scale", type=float, default=1.0, help="image resolution factor")
    p.add_argument("--frames", help="frame positions START:STOP (keyframes for nuScenes), default all")
    p.add_argument("--no-lidar", action="store_true", help="no LiDAR (Waymo: needs no lidar file)")


convert.add_arguments = _convert_args  # type: ignore[attr-defined]


def check(args: argparse.Namespace) -> int:
    """Validate a scene's metadata and files; print a table (exit 1 when a check fails)."""
    from vadgs.data import load_dgp, validate_scene

    if args.dgp:
        try:
            scene = load_dgp(_scene_arg(args.scene), scale=args.scale, validate="none")
        except (ValueError, FileNotFoundError) as e:
            print(f"error  {args.scene}: {e}")
            return 1
        report = validate_scene(scene, full=args.full)
    else:
        report = validate_scene(_scene_arg(args.scene), full=args.full, scale=args.scale)
    print(report.format_table())
    level = "every file decoded" if args.full else "headers only; --full decodes every file"
    n = len(report.errors)
    print(f"{report.scene}: {'ok' if report.ok else f'{n} error(s)'} ({len(report.rows)} checks, {level})")
    return 0 if report.ok else 1


def _check_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("scene", nargs="?", help="scene folder (default: the bundled sample)")
    p.add_argument("--full", action="store_true", help="decode every image, depth map, instance map, sweep")
    p.add_argument("--scale", type=_positive_float, default=1.0, help="resolution factor to check against")
    p.add_argument("--dgp", action="store_true", help="SCENE is a DGP scene folder")


check.add_arguments = _check_args  # type: ignore[attr-defined]
