"""A COLMAP project written with pycolmap from the bundled sample scene (known cameras and points).

Every view of the sample (8 frames x 3 cameras, 240x144) becomes a registered image named by its
path under ``images/`` (``front/016.png``); each rig camera a COLMAP camera; a seeded subset of
the static LiDAR points becomes the 3D points, observed (the TRACK table) by every view they
project into, at COLMAP's own projection of them (distortion included).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from vadgs.data import load_scene, sample_scene_path
from vadgs.geometry import invert_rigid
from vadgs.geometry.camera import observing_views


def write_sample_colmap(
    root: Path,
    model: str = "PINHOLE",
    k: float = 0.0,
    n_points: int = 1500,
    link_images: bool = True,
    name_prefix: str = "",
    shift: tuple[float, float, float] = (0.0, 0.0, 0.0),
    crop: dict[str, tuple[int, int]] | None = None,
    text: bool = False,
) -> dict:
    """Write ``root/sparse/0`` (and ``root/images`` -> the sample's images).

    Args:
        root: the project folder.
        model: ``PINHOLE``, ``SIMPLE_RADIAL`` (``k``) or ``OPENCV`` (``k1 = k``).
        k: radial distortion of the distorted models.
        n_points: static LiDAR points kept (seeded).
        link_images: make ``root/images`` a symlink to the sample's images.
        name_prefix: prepended to every image name (a mismatching model when not empty).
        shift: added to every camera centre and point (a model in another world frame).
        crop: ``{camera: (H, W)}``: that camera's images keep their top-left ``H x W`` (same
            intrinsics, observations outside dropped): a rig of several image sizes. The
            images are then copied into ``root/images`` (``link_images`` ignored).
        text: write the model as text (``cameras.txt``, ...) instead of binary.

    Returns:
        ``{"scene", "names", "points", "obs"}``: the sample scene (full resolution), the image
        name of each of its views, the ``(P, 3)`` points and their observations as a set of
        ``(point, sample view)`` pairs.
    """
    import pycolmap

    scene = load_scene(sample_scene_path())
    images_root = sample_scene_path() / "images"
    names = [str(Path(v.image).relative_to(images_root)) for v in scene.views]
    rec = pycolmap.Reconstruction()
    cam_ids = {}
    crop = crop or {}
    for i, (cname, info) in enumerate(scene.cameras_info.items()):
        h, w = crop.get(cname, info.image_size)
        fx, fy = float(info.K[0, 0]), float(info.K[1, 1])
        cx, cy = float(info.K[0, 2]) + 0.5, float(info.K[1, 2]) + 0.5  # COLMAP pixel convention
        params = {
            "PINHOLE": [fx, fy, cx, cy],
            "SIMPLE_RADIAL": [fx, cx, cy, k],
            "OPENCV": [fx, fy, cx, cy, k, 0.0, 0.0, 0.0],
        }[model]
        cam = pycolmap.Camera.create_from_model_name(i + 1, model, fx, w, h)
        cam.params = params
        rec.add_camera_with_trivial_rig(cam)
        cam_ids[cname] = i + 1
    sweeps = [scene.lidar(f.index) for f in scene.frames]
    static = torch.cat(
        [s.points[~torch.isin(s.instance, torch.tensor(sorted(scene.tracks)))] for s in sweeps]
    )
    gen = torch.Generator().manual_seed(0)
    pts = static[torch.randperm(static.shape[0], generator=gen)[:n_points]].double()
    pts = pts + torch.tensor(shift, dtype=torch.float64)
    pi, vi = observing_views(pts.float(), scene.cameras())
    obs: dict[int, dict[int, int]] = {}
    for v in scene.views:
        c2w = v.cam_to_world.double().clone()
        c2w[:3, 3] += torch.tensor(shift, dtype=torch.float64)
        cfw = invert_rigid(c2w)[:3].numpy()
        sel = pi[vi == v.index].numpy()
        cam = rec.cameras[cam_ids[v.camera]]
        cam_pts = pts.numpy()[sel] @ cfw[:, :3].T + cfw[:, 3]
        uv = np.asarray(cam.img_from_cam(cam_pts)).reshape(-1, 2)
        if v.camera in crop:  # observations in the cropped part only
            inside = (uv[:, 0] < cam.width) & (uv[:, 1] < cam.height)
            sel, uv = sel[inside], uv[inside]
        image = pycolmap.Image(
            name=name_prefix + names[v.index], keypoints=uv, camera_id=cam_ids[v.camera], image_id=v.index + 1
        )
        rec.add_image_with_trivial_frame(image, pycolmap.Rigid3d(cfw))
        obs[v.index] = {int(j): kp for kp, j in enumerate(sel)}
    pairs = set()
    for j in range(pts.shape[0]):
        track = pycolmap.Track()
        for view, kps in obs.items():
            if j in kps:
                track.add_element(view + 1, kps[j])
                pairs.add((j, view))
        rec.add_point3D(pts[j].numpy(), track, np.array([128, 128, 128], dtype=np.uint8))
    sparse = root / "sparse" / "0"
    sparse.mkdir(parents=True, exist_ok=True)
    rec.write_text(str(sparse)) if text else rec.write(str(sparse))
    if crop:
        from PIL import Image

        for v, name in zip(scene.views, names):
            dst = root / "images" / name
            dst.parent.mkdir(parents=True, exist_ok=True)
            h, w = crop.get(v.camera, scene.cameras_info[v.camera].image_size)
            Image.fromarray(np.asarray(Image.open(images_root / name))[:h, :w]).save(dst)
    elif link_images:
        (root / "images").symlink_to(images_root, target_is_directory=True)
    return {"scene": scene, "names": names, "points": pts, "obs": pairs}
