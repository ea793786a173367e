"""Load a DGP driving scene, print a summary and draw its LiDAR over one camera image.

Usage::

    python examples/data_dgp.py [SCENE_DIR] [--out docs/img/data_dgp_lidar.png]

``SCENE_DIR`` defaults to ``../shared/data/real/dgp_test_scene/scene_02`` (the data is not part
of the repository; see ``docs/data.md``).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch
from PIL import Image

from vadgs.data import load_dgp
from vadgs.geometry import project_points

REPO = Path(__file__).resolve().parents[1]
DEFAULT = REPO.parent / "shared" / "data" / "real" / "dgp_test_scene" / "scene_02"


def _turbo(t: np.ndarray) -> np.ndarray:
    """A small blue→green→red colour ramp for t in [0, 1] (near = red)."""
    t = np.clip(t, 0, 1)[:, None]
    stops = np.array([[220, 40, 30], [250, 200, 40], [60, 200, 90], [40, 120, 240]], dtype=np.float64)
    pos = t * (len(stops) - 1)
    i = np.minimum(pos.astype(int), len(stops) - 2)
    f = pos - i
    return (stops[i[:, 0]] * (1 - f) + stops[i[:, 0] + 1] * f).astype(np.uint8)


def lidar_overlay(scene, view_id: int, max_depth: float = 50.0) -> Image.Image:
    """The view's image with its frame's LiDAR drawn as 2×2 dots coloured by depth."""
    view = scene.views[view_id]
    img = (scene.load_images([view_id])[0].permute(1, 2, 0).numpy() * 255).astype(np.uint8)
    cams = scene.cameras([view_id])
    uv, z = project_points(scene.lidar(view.frame).points[None], cams.K, cams.world_to_cam)
    uv, z = uv[0], z[0]
    H, W = scene.image_size(view_id)
    px = uv.round().long()
    ok = (
        (z > 0.5)
        & (z < max_depth)
        & (px[:, 0] >= 0)
        & (px[:, 0] < W - 1)
        & (px[:, 1] >= 0)
        & (px[:, 1] < H - 1)
    )
    order = torch.argsort(z[ok], descending=True)  # far first, near drawn on top
    px, depth = px[ok][order].numpy(), z[ok][order].numpy()
    colours = _turbo(depth / max_depth)
    out = img.copy()
    for dy in (0, 1):
        for dx in (0, 1):
            out[px[:, 1] + dy, px[:, 0] + dx] = colours
    return Image.fromarray(out)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("scene_dir", nargs="?", default=str(DEFAULT))
    parser.add_argument("--camera", default="CAMERA_01")
    parser.add_argument("--frame", type=int, default=1)
    parser.add_argument("--scale", type=float, default=0.4)
    parser.add_argument("--out", default=str(REPO / "docs" / "img" / "data_dgp_lidar.png"))
    args = parser.parse_args()

    scene = load_dgp(args.scene_dir, scale=args.scale)
    print(scene)
    for name, cam in scene.cameras_info.items():
        K = cam.K
        print(
            f"  {name}: {cam.image_size[1]}x{cam.image_size[0]} fx={K[0, 0]:.1f} fy={K[1, 1]:.1f} "
            f"cx={K[0, 2]:.1f} cy={K[1, 2]:.1f}"
        )
    for f in scene.frames:
        lid = scene.lidar(f.index)
        print(
            f"  frame {f.index}: t={f.timestamp:.3f} s, ego at {f.ego_to_world[:3, 3].numpy().round(2)}, "
            f"{len(lid.points)} LiDAR points, {int((lid.instance > 0).sum())} inside boxes"
        )
    for tid, t in scene.tracks.items():
        moved = (t.object_to_world[t.valid, :3, 3] - t.object_to_world[t.valid][:1, :3, 3]).norm(dim=-1).max()
        print(f"  track {tid}: {t.class_name}, size_lwh={t.size_lwh.numpy().round(2)}, moved {moved:.2f} m")

    image = lidar_overlay(scene, scene.view_id(args.frame, args.camera))
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    image.quantize(colors=128, method=Image.Quantize.MEDIANCUT).save(out, optimize=True)  # small for the docs
    print(f"wrote {out} ({out.stat().st_size // 1024} KB)")


if __name__ == "__main__":
    main()
