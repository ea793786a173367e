"""Write any :class:`~vadgs.data.scene.Scene` in the benchmark scene format (``scene.json``).

Used to convert a nuScenes scene or a Waymo segment once, so that ``vadgs train DIR`` and every
tool that reads :func:`~vadgs.data.load_scene` work on it (``vadgs convert`` on the command line).
"""

from __future__ import annotations

import functools
import shutil
from pathlib import Path

import numpy as np
from PIL import Image

from vadgs.data.box_masks import box_instance_map
from vadgs.data.scene import LidarFrame, Scene
from vadgs.io import atomic_write, safe_filename, write_json

__all__ = ["export_scene", "write_lidar_npz"]


def _list(t) -> list:
    return [[float(v) for v in row] for row in t.double().tolist()]


def write_lidar_npz(path: str | Path, lidar: LidarFrame) -> None:
    """Write ``lidar`` atomically as a benchmark LiDAR ``.npz``.

    :func:`~vadgs.data.scene.read_lidar_npz` reads it back: ``points`` float32 ``(N, 3)``,
    ``instance`` int32 ``(N,)``, ``origin`` float32 ``(3,)``.

    Example:
        >>> import tempfile
        >>> import torch
        >>> from vadgs.data.scene import read_lidar_npz
        >>> lf = LidarFrame(torch.rand(5, 3), torch.arange(5), torch.zeros(3))
        >>> with tempfile.TemporaryDirectory() as d:
        ...     write_lidar_npz(Path(d) / "000000.npz", lf)
        ...     torch.equal(read_lidar_npz(Path(d) / "000000.npz").points, lf.points)
        True
    """
    arrays = {
        "points": lidar.points.float().numpy(),
        "instance": lidar.instance.numpy().astype(np.int32),
        "origin": lidar.origin.float().numpy(),
    }

    def save(tmp: Path) -> None:
        np.savez(tmp, **arrays)  # type: ignore[arg-type]  # stubs: **arrays might fill allow_pickle

    atomic_write(Path(path), save)


def export_scene(scene: Scene, out_dir: str | Path, lidar: bool = True, box_masks: bool = False) -> Path:
    """Write a scene as ``scene.json`` + ``images/<camera>/<frame>.png`` + ``lidar/<frame>.npz``.

    Images are written as 8-bit PNG at the scene's resolution (``image_size``, i.e. after the
    ``scale`` it was loaded with), with ``K`` to match; loading the result with
    :func:`~vadgs.data.load_scene` (``scale=1``) gives the same cameras, poses, LiDAR (world
    points, instance ids, origin), instances, tracks (the valid frames of each) and split.
    Depth and instance maps are not written (a converted real scene has none; ``box_masks`` paints
    the test views' from the boxes); the tracks' meshes are
    copied to ``gt/`` so that the folder is self-contained. Camera names become folder names made
    safe by :func:`vadgs.io.safe_filename`.

    Args:
        scene: the scene (e.g. from :func:`~vadgs.data.load_nuscenes`).
        out_dir: the folder to write (created; existing files are overwritten).
        lidar: also write each frame's LiDAR (if the scene has any).
        box_masks: write an instance map for each test view, painted from the tracks' boxes
            (:func:`~vadgs.data.box_masks.box_instance_map`; uint16 PNG in ``instances/``), so that
            PSNR* is measured on the converted scene.

    Returns:
        The path of the written ``scene.json``.

    Example:
        >>> import tempfile
        >>> from vadgs.data import load_scene, sample_scene_path
        >>> scene = load_scene(sample_scene_path())
        >>> with tempfile.TemporaryDirectory() as d:
        ...     again = load_scene(export_scene(scene, d, lidar=False))
        ...     again.num_views, again.image_size(0), sorted(again.tracks) == sorted(scene.tracks)
        (24, (144, 240), True)
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    cameras = {
        name: {
            "width": c.image_size[1],
            "height": c.image_size[0],
            "K": _list(c.K),
            **({"cam_to_ego": _list(c.cam_to_ego)} if c.cam_to_ego is not None else {}),
        }
        for name, c in scene.cameras_info.items()
    }
    frames = []
    test_views = set(scene.test_views) if box_masks else set()
    for f in scene.frames:
        views = []
        for vid in f.view_ids:
            v = scene.views[vid]
            rel = f"images/{safe_filename(v.camera)}/{f.index:06d}.png"
            img = scene.load_images([vid])[0]  # a fresh tensor: rounded to 8 bits in place
            pil = Image.fromarray(img.clamp_(0, 1).mul_(255).round_().byte().permute(1, 2, 0).numpy())
            atomic_write(out / rel, functools.partial(pil.save, format="PNG"))
            vm = {"camera": v.camera, "image": rel, "cam_to_world": _list(v.cam_to_world)}
            if vid in test_views:
                vm["instances"] = _write_box_mask(scene, vid, out, f"{safe_filename(v.camera)}/{f.index:06d}")
            views.append(vm)
        fm: dict = {"index": f.index, "timestamp": f.timestamp, "views": views}
        if f.ego_to_world is not None:
            fm["ego_to_world"] = _list(f.ego_to_world)
        if lidar and scene.lidar_loader is not None:
            rel = f"lidar/{f.index:06d}.npz"
            write_lidar_npz(out / rel, scene.lidar(f.index))
            fm["lidar"] = rel
        frames.append(fm)
    meta = {
        "name": scene.name,
        "conventions": "world z up, metres; OpenCV cameras; cam_to_world; pixel centres at integers",
        "cameras": cameras,
        "frames": frames,
        "instances": [
            {"id": i.id, "name": i.name, "class": i.class_name, "dynamic": i.dynamic}
            for i in scene.instances.values()
        ],
        "tracks": [
            {
                "id": t.id,
                "class": t.class_name,
                "size_lwh": [float(v) for v in t.size_lwh.tolist()],
                "object_to_world": {
                    str(scene.frames[p].index): _list(t.object_to_world[p])
                    for p in range(len(scene.frames))
                    if bool(t.valid[p])
                },
                **(
                    {"mesh": _copy_mesh(t.mesh, out, t.id)} if t.mesh is not None and t.mesh.is_file() else {}
                ),
            }
            for t in scene.tracks.values()
        ],
        "split": {"train_frames": list(scene.train_frames), "test_frames": list(scene.test_frames)},
    }
    return write_json(out / "scene.json", meta, indent=None)  # last: a folder with it is complete


def _write_box_mask(scene: Scene, view: int, out: Path, stem: str) -> str:
    """Write the view's :func:`box_instance_map` as a uint16 PNG under ``out/instances/``; its path there."""
    ids = box_instance_map(scene, view)
    if int(ids.max()) > 65535:
        raise ValueError(f"box_masks: track id {int(ids.max())} does not fit a uint16 instance map")
    rel = f"instances/{stem}.png"
    pil = Image.fromarray(ids.numpy().astype(np.uint16))
    atomic_write(out / rel, functools.partial(pil.save, format="PNG"))
    return rel


def _copy_mesh(mesh: Path, out: Path, track_id: int) -> str:
    """Copy a track's mesh into ``out/gt/`` (the exported scene stays self-contained); its path there."""
    rel = f"gt/object_{int(track_id)}{mesh.suffix}"
    atomic_write(out / rel, lambda tmp: shutil.copyfile(mesh, tmp))
    return rel
