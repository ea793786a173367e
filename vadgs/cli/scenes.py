"""Commands on a scene's data: ``vadgs visibility``, ``vadgs convert``, ``vadgs check``."""

from __future__ import annotations

import json
import re
import time
from dataclasses import dataclass
from typing import Annotated, Literal

import tyro

from vadgs.checks import check_at_least, check_positive
from vadgs.cli._common import Command, Flag, Positional, _check_out_dir, _scene_arg
from vadgs.io import write_json

__all__ = ["CheckCommand", "ConvertCommand", "VisibilityCommand"]

#: An optional scene folder (default: the bundled sample).
SceneArg = Annotated[str | None, Positional, tyro.conf.arg(metavar="SCENE")]


@dataclass(frozen=True)
class VisibilityCommand(Command):
    """Voxel visibility reasoning on a scene: voxelise LiDAR, z-buffer one view, write a PNG panel."""

    scene: SceneArg = None
    """scene folder (default: the bundled sample)"""
    out: str = "outputs/visibility"
    """output folder"""
    view: int | None = None
    """view index (default: a middle training view)"""
    voxel_size: float = 0.2
    """voxel edge in metres"""
    scale: float = 1.0
    """image resolution factor"""
    only_observed: Flag = False
    """rasterise only voxels observed by the view"""

    def __post_init__(self) -> None:
        super().__post_init__()
        check_positive(self, "voxel_size", "scale")
        if self.view is not None:
            check_at_least(self, 0, "view")

    def main(self) -> int:
        """Write the panel and visibility.json; 0."""
        from vadgs.data import load_scene
        from vadgs.data.lidar import accumulate_lidar
        from vadgs.geometry import ZBufferConfig, rasterize_voxels, voxelize
        from vadgs.viz import colorize_depth, colorize_index, image_to_uint8, save_panel

        out = _check_out_dir(self.out)
        scene = load_scene(_scene_arg(self.scene), scale=self.scale)
        t0 = time.perf_counter()
        acc = accumulate_lidar(scene)
        grid = voxelize(acc.points, self.voxel_size, acc.point_views, scene.num_views)
        t1 = time.perf_counter()
        view = self.view if self.view is not None else scene.train_views[len(scene.train_views) // 2]
        raster = rasterize_voxels(
            grid, scene.cameras([view]), [view], ZBufferConfig(only_observed=self.only_observed)
        )
        t2 = time.perf_counter()
        image = scene.load_images([view])[0]
        gt = scene.load_depths([view])[0, 0] if scene.views[view].depth is not None else None
        depth = raster.depth[0, 0]
        panels = [image_to_uint8(image), colorize_depth(depth), colorize_index(raster.index[0])]
        titles = ["image", f"voxel depth ({self.voxel_size} m voxels)", "pixel -> voxel index"]
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
                float(((depth - gt).abs()[both] < self.voxel_size).float().mean()) if both.any() else 0.0, 4
            )
        png = save_panel(panels, titles, out / f"visibility_view{view:03d}.png", columns=2)
        write_json(out / "visibility.json", metrics)
        print(json.dumps(metrics, indent=2))
        print(f"wrote {png}")
        return 0


@dataclass(frozen=True)
class ConvertCommand(Command):
    """Convert a nuScenes scene or a Waymo v2 segment into the benchmark format (``scene.json``)."""

    dataset: Annotated[Literal["nuscenes", "waymo"], Positional, tyro.conf.arg(metavar="{nuscenes,waymo}")]
    """the dataset of SRC"""
    src: Annotated[str, Positional, tyro.conf.arg(metavar="SRC")]
    """nuScenes dataroot, or the Waymo v2 split folder holding the components"""
    scene: str
    """nuScenes scene name (scene-0061) or Waymo segment name"""
    out: str
    """output folder for scene.json, images/, lidar/"""
    version: str = "v1.0-mini"
    """nuScenes table folder (v1.0-mini, v1.0-trainval)"""
    cameras: str | None = None
    """comma-separated camera names (default all)"""
    scale: float = 1.0
    """image resolution factor"""
    frames: str | None = None
    """frame positions START:STOP or one position (keyframes for nuScenes; default all)"""
    no_lidar: Flag = False
    """no LiDAR (Waymo: needs no lidar file)"""

    def __post_init__(self) -> None:
        super().__post_init__()
        check_positive(self, "scale")
        if self.frames is not None and not re.fullmatch(r"\d*:\d+|\d+", self.frames):
            raise ValueError(f"frames: expected START:STOP or one position, got {self.frames!r}")

    def main(self) -> int:
        """Write the scene in the benchmark format; 0."""
        from vadgs.data import export_scene, load_nuscenes, load_waymo

        cameras = self.cameras.split(",") if self.cameras else None
        frames = None
        if self.frames:
            start, _, stop = self.frames.partition(":")
            frames = range(int(start or 0), int(stop)) if stop else [int(start)]
        if self.dataset == "nuscenes":
            scene = load_nuscenes(
                self.src, self.scene, version=self.version, cameras=cameras, scale=self.scale, frames=frames
            )
        else:
            lasers = None if self.no_lidar else ("TOP",)  # --no-lidar: a segment without the lidar component
            scene = load_waymo(
                self.src, self.scene, cameras=cameras, scale=self.scale, frames=frames, lasers=lasers
            )
        path = export_scene(scene, self.out, lidar=not self.no_lidar)
        print(f"{scene!r} -> {path}")
        return 0


@dataclass(frozen=True)
class CheckCommand(Command):
    """Validate a scene's metadata and files; print a table (exit 1 when a check fails)."""

    scene: SceneArg = None
    """scene folder (default: the bundled sample)"""
    full: Flag = False
    """decode every image, depth map, instance map, sweep"""
    scale: float = 1.0
    """resolution factor to check against"""
    dgp: Flag = False
    """SCENE is a DGP scene folder"""

    def __post_init__(self) -> None:
        super().__post_init__()
        check_positive(self, "scale")

    def main(self) -> int:
        """Print the report; 0 when every check passes, else 1."""
        from vadgs.data import load_dgp, validate_scene

        if self.dgp:
            try:
                scene = load_dgp(_scene_arg(self.scene), scale=self.scale, validate="none")
            except (ValueError, FileNotFoundError) as e:
                print(f"error  {self.scene}: {e}")
                return 1
            report = validate_scene(scene, full=self.full)
        else:
            report = validate_scene(_scene_arg(self.scene), full=self.full, scale=self.scale)
        print(report.format_table())
        level = "every file decoded" if self.full else "headers only; --full decodes every file"
        n = len(report.errors)
        print(
            f"{report.scene}: {'ok' if report.ok else f'{n} error(s)'} ({len(report.rows)} checks, {level})"
        )
        return 0 if report.ok else 1
