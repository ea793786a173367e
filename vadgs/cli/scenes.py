"""Commands on a scene's data: ``vadgs visibility``, ``vadgs convert``, ``vadgs check``.

``visibility`` and ``check`` take what ``vadgs train`` takes: a benchmark scene folder
(``scene.json``), a COLMAP model or project folder (detected), or a DGP scene with ``--dgp``; one
function decides the kind (:func:`vadgs.train.scenes.scene_ref`).
"""

from __future__ import annotations

import contextlib
import json
import re
import shutil
import time
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Literal

import tyro

from vadgs.checks import checked, float_field, int_field
from vadgs.cli._common import Command, Flag, Positional, check_out_dir, scene_arg
from vadgs.io import write_json

__all__ = ["CheckCommand", "ConvertCommand", "VisibilityCommand"]

#: An optional scene folder (default: the bundled sample).
SceneArg = Annotated[str | None, Positional, tyro.conf.arg(metavar="SCENE")]


def _scene_ref(scene: str | None, dgp: bool, scale: float):
    """The reference of SCENE (default: the bundled sample): its kind decided by ``scene_ref``."""
    from vadgs.train.scenes import scene_ref

    return scene_ref(scene_arg(scene), "dgp" if dgp else None, scale=scale)


@contextlib.contextmanager
def _new_folder(path: Path):
    """Remove ``path`` (and the parents made for it) again when the block fails, if it was new."""
    made = [p for p in (path, *path.parents) if not p.exists()]
    try:
        yield
    except BaseException:
        if made:
            shutil.rmtree(made[0], ignore_errors=True)  # the top folder made: nothing was there before
        raise


@dataclass(frozen=True)
class VisibilityCommand(Command):
    """Voxel visibility reasoning on a scene: voxelise LiDAR or SfM points, z-buffer a view, write a panel.

    SCENE is what ``vadgs train`` takes: a benchmark scene (LiDAR), a COLMAP model or project
    (its SfM points and their observations; distorted cameras are read by their pinhole part), or
    a DGP scene with ``--dgp``.
    """

    scene: SceneArg = None
    """scene folder: benchmark (scene.json), COLMAP model or project (detected), DGP with --dgp
    (default: the bundled sample)"""
    out: str = "outputs/visibility"
    """output folder"""
    view: int | None = checked(None, int_field(0, optional=True))
    """view index (default: a middle training view)"""
    voxel_size: float = checked(0.2, float_field(0, lo_open=True))
    """voxel edge in metres"""
    scale: float = checked(1.0, float_field(0, lo_open=True))
    """image resolution factor"""
    only_observed: Flag = False
    """rasterise only voxels observed by the view"""
    dgp: Flag = False
    """SCENE is a DGP scene folder"""

    def main(self) -> int:
        """Write the panel and visibility.json; 0."""
        from vadgs.train.scenes import read_scene

        out = check_out_dir(self.out, create=False)  # created once the scene has opened
        scene = read_scene(_scene_ref(self.scene, self.dgp, self.scale))
        if self.view is not None and self.view >= scene.num_views:
            raise ValueError(
                f"--view: expected < {scene.num_views} (the views of {scene.name}), got {self.view}"
            )
        with _new_folder(out):
            return self._write(scene, check_out_dir(out))

    def _write(self, scene, out: Path) -> int:
        from vadgs.data.lidar import accumulate_lidar
        from vadgs.data.observations import sfm_observations
        from vadgs.geometry import ZBufferConfig, rasterize_voxels, voxelize
        from vadgs.viz import colorize_depth, colorize_index, image_to_uint8, save_panel

        t0 = time.perf_counter()
        if scene.lidar_loader is not None:
            acc = accumulate_lidar(scene)
            points, point_views, source = acc.points, acc.point_views, "lidar"
        elif scene.sfm_points is not None:
            points, point_views = sfm_observations(scene)
            source = "sfm"
        else:
            raise ValueError(f"scene {scene.name!r}: no LiDAR and no SfM points to voxelise")
        grid = voxelize(points, self.voxel_size, point_views, scene.num_views)
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
            "points_from": source,
            f"{source}_points": int(points.shape[0]),
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
    """Convert a nuScenes scene, Waymo v2 segment, PandaSet sequence or Argoverse 2 log (scene.json)."""

    dataset: Annotated[
        Literal["nuscenes", "waymo", "pandaset", "argoverse2"],
        Positional,
        tyro.conf.arg(metavar="{nuscenes,waymo,pandaset,argoverse2}"),
    ]
    """the dataset of SRC"""
    src: Annotated[str, Positional, tyro.conf.arg(metavar="SRC")]
    """nuScenes dataroot, the Waymo v2 split folder holding the components, a PandaSet sequence folder
    or an Argoverse 2 log folder"""
    out: str
    """output folder for scene.json, images/, lidar/"""
    scene: str | None = None
    """nuScenes scene name (scene-0061) or Waymo segment name (required for those two)"""
    version: str = "v1.0-mini"
    """nuScenes table folder (v1.0-mini, v1.0-trainval)"""
    cameras: str | None = None
    """comma-separated camera names (default all)"""
    scale: float = checked(1.0, float_field(0, lo_open=True))
    """image resolution factor"""
    frames: str | None = None
    """frame positions START:STOP or one position (nuScenes keyframes, Argoverse 2 sweeps; default all)"""
    no_lidar: Flag = False
    """no LiDAR (Waymo: needs no lidar file)"""
    lidar: Literal["pandar64", "pandargt", "both"] = "pandar64"
    """PandaSet: the LiDAR points kept (pandar64: the 360 one, pandargt: the forward one, both)"""
    lidars: str | None = None
    """Argoverse 2: comma-separated LiDARs of each frame, up_lidar,down_lidar (default both)"""
    undistort: Flag = False
    """Argoverse 2: undistort the images with k1, k2, k3 (default: ignore them, as the av2 devkit)"""

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.frames is not None and not re.fullmatch(r"\d*:\d+|\d+", self.frames):
            raise ValueError(f"frames: expected START:STOP or one position, got {self.frames!r}")
        if self.scene is None and self.dataset in ("nuscenes", "waymo"):
            raise ValueError(f"--scene: required for {self.dataset} (the scene or segment name in SRC)")
        for name, value in (("lidars", self.lidars is not None), ("undistort", self.undistort)):
            if self.dataset != "argoverse2" and value:
                raise ValueError(f"{name}: an Argoverse 2 option, got dataset {self.dataset}")
        if self.dataset != "pandaset" and self.lidar != "pandar64":
            raise ValueError(f"lidar: a PandaSet option, got dataset {self.dataset}")

    def main(self) -> int:
        """Write the scene in the benchmark format; 0."""
        from vadgs.data import export_scene

        cameras = self.cameras.split(",") if self.cameras else None
        frames = None
        if self.frames:
            start, _, stop = self.frames.partition(":")
            frames = range(int(start or 0), int(stop)) if stop else [int(start)]
        box_masks = False
        if self.dataset == "argoverse2":
            scene = self._argoverse2(cameras, frames)
        elif self.dataset == "nuscenes":
            from vadgs.data import load_nuscenes

            assert self.scene is not None  # checked in __post_init__
            scene = load_nuscenes(
                self.src, self.scene, version=self.version, cameras=cameras, scale=self.scale, frames=frames
            )
        elif self.dataset == "waymo":
            from vadgs.data import load_waymo

            assert self.scene is not None
            lasers = None if self.no_lidar else ("TOP",)  # --no-lidar: a segment without the lidar component
            scene = load_waymo(
                self.src, self.scene, cameras=cameras, scale=self.scale, frames=frames, lasers=lasers
            )
        else:
            from vadgs.data import load_pandaset

            lidar = None if self.no_lidar else self.lidar
            scene = load_pandaset(self.src, cameras=cameras, scale=self.scale, frames=frames, lidar=lidar)
            box_masks = True  # the test views' instance maps from the cuboids: PSNR* is measured
        path = export_scene(scene, self.out, lidar=not self.no_lidar, box_masks=box_masks)
        print(f"{scene!r} -> {path}")
        return 0

    def _argoverse2(self, cameras, frames):
        """The Argoverse 2 log SRC, its image/sweep matching printed (dropped sweeps once, not warned)."""
        from vadgs.data.argoverse2 import ARGOVERSE2_LIDARS, load_argoverse2
        from vadgs.data.argoverse2_tables import argoverse2_sync

        lidars = None if self.no_lidar else (self.lidars.split(",") if self.lidars else ARGOVERSE2_LIDARS)
        print(argoverse2_sync(self.src, cameras, frames).summary())
        with warnings.catch_warnings():
            warnings.filterwarnings("ignore", message="Argoverse 2 log", category=UserWarning)
            return load_argoverse2(
                self.src,
                cameras=cameras,
                scale=self.scale,
                frames=frames,
                lidars=lidars,
                undistort=self.undistort,
            )


@dataclass(frozen=True)
class CheckCommand(Command):
    """Validate a scene's metadata and files; print a table (exit 1 when a check fails).

    SCENE is what ``vadgs train`` takes: a benchmark scene, a COLMAP model or project (detected;
    its distorted cameras are checked as they are, not undistorted) or a DGP scene with ``--dgp``.
    """

    scene: SceneArg = None
    """scene folder: benchmark (scene.json), COLMAP model or project (detected), DGP with --dgp
    (default: the bundled sample)"""
    full: Flag = False
    """decode every image, depth map, instance map, sweep"""
    scale: float = checked(1.0, float_field(0, lo_open=True))
    """resolution factor to check against"""
    dgp: Flag = False
    """SCENE is a DGP scene folder"""

    def main(self) -> int:
        """Print the report; 0 when every check passes, else 1."""
        from vadgs.data import validate_scene
        from vadgs.data.checks import ValidationReport, ValidationRow
        from vadgs.train.scenes import BenchmarkRef, read_scene

        path = scene_arg(self.scene)
        notes: list[str] = []
        try:
            ref = _scene_ref(self.scene, self.dgp, self.scale)
            if isinstance(ref, BenchmarkRef):  # a scene.json that does not parse is one row
                report = validate_scene(ref.path, full=self.full, scale=self.scale)
            else:
                with warnings.catch_warnings(record=True) as caught:
                    warnings.simplefilter("always")
                    scene = read_scene(ref, validate="none")
                notes = list(dict.fromkeys(str(w.message) for w in caught))
                report = validate_scene(scene, full=self.full)
        except (ValueError, FileNotFoundError) as e:
            row = ValidationRow("scene", str(path), "error", str(e))
            report = ValidationReport(str(path), (row,), self.full)
        print(report.format_table())
        for note in notes:
            print(f"note: {note}")
        level = "every file decoded" if self.full else "headers only; --full decodes every file"
        n = len(report.errors)
        print(
            f"{report.scene}: {'ok' if report.ok else f'{n} error(s)'} ({len(report.rows)} checks, {level})"
        )
        return 0 if report.ok else 1
