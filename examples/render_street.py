"""Render LiDAR-initialised Gaussians of street_a with vadgs.render and save a PNG.

    python examples/render_street.py [--out docs/img/render_street.png] [--frame 0]

Each LiDAR point of frames f..f+2 becomes a flat Gaussian (scale from the mean distance to its
3 nearest neighbours as in 3DGS, a tenth of that along the PCA normal of its neighbourhood)
coloured by projecting it into the camera images of its own frame. The front camera of frame f
renders colour, depth and normals, saved side by side. Without ../shared/data/street_a it fits
Gaussians to a photo crop instead and renders those.
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

import numpy as np
import torch
from kornia.geometry.conversions import rotation_matrix_to_quaternion
from PIL import Image

from vadgs.render import rasterize_gaussians

STREET = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "street_a"


def street_gaussians(frame: int):
    from scipy.spatial import cKDTree

    from vadgs.data import load_scene

    scene = load_scene(STREET)
    pts, cols = [], []
    for f in range(frame, frame + 3):
        p = scene.lidar(f).points.float()
        views = [v for v in scene.frames[f].view_ids]
        cams = scene.cameras(views)
        images = scene.load_images(views)
        col = torch.full((len(p), 3), 0.5)
        for i in range(len(views)):
            p_cam = (cams.world_to_cam[i, :3, :3] @ p.T).T + cams.world_to_cam[i, :3, 3]
            uv = (p_cam[:, :2] / p_cam[:, 2:].clamp_min(1e-6)) @ cams.K[i, :2, :2].T + cams.K[i, :2, 2]
            h, w = cams.image_size
            u, v = uv[:, 0].round().long(), uv[:, 1].round().long()
            ok = (p_cam[:, 2] > 0.5) & (u >= 0) & (u < w) & (v >= 0) & (v < h)
            col[ok] = images[i, :, v[ok], u[ok]].T
        pts.append(p)
        cols.append(col)
    means, colors = torch.cat(pts), torch.cat(cols)
    # Flat Gaussians (surfels) aligned with the local point distribution, so that the rendered
    # normals mean something: PCA of the 8 nearest neighbours, thinnest along the normal.
    dist, idx = cKDTree(means.numpy()).query(means.numpy(), k=8)
    nb = means[torch.from_numpy(idx)] - means[:, None]
    _, axes = torch.linalg.eigh(nb.transpose(1, 2) @ nb)  # ascending: column 0 is the normal
    rot = torch.stack([axes[..., 2], axes[..., 1], torch.linalg.cross(axes[..., 2], axes[..., 1])], -1)
    quats = rotation_matrix_to_quaternion(rot)  # wxyz, local z = normal
    s = torch.from_numpy(np.sqrt((dist[:, 1:4] ** 2).mean(1))).float().clamp_min(1e-3)
    scales = torch.stack([s, s, 0.1 * s], -1)
    opacities = torch.full((len(means),), 0.9)
    cams = scene.cameras([scene.view_id(frame, "front")])
    return (means, quats, scales, opacities, colors), cams.world_to_cam, cams.K, cams.image_size


def photo_gaussians(steps: int = 200):
    from skimage import data, transform

    img = transform.resize(data.astronaut()[20:276, 140:396], (96, 96), anti_aliasing=True)
    target = torch.tensor(img, dtype=torch.float32).permute(2, 0, 1)[None]
    n, f = 4000, 96.0
    K = torch.tensor([[[f, 0, 47.5], [0, f, 47.5], [0, 0, 1.0]]])
    w2c = torch.eye(4)[None]
    g = torch.Generator().manual_seed(0)
    means = torch.cat([(torch.rand(n, 2, generator=g) - 0.5) * 1.1, torch.ones(n, 1)], 1).requires_grad_(True)
    log_s = torch.full((n, 3), math.log(1.5 / f)).requires_grad_(True)
    quats = torch.randn(n, 4, generator=g).requires_grad_(True)
    lo, lc = torch.zeros(n).requires_grad_(True), torch.zeros(n, 3).requires_grad_(True)
    opt = torch.optim.Adam([{"params": [means], "lr": 2e-3}, {"params": [log_s, quats, lo, lc], "lr": 2e-2}])
    for _ in range(steps):
        out = rasterize_gaussians(means, quats, log_s.exp(), lo.sigmoid(), lc.sigmoid(), w2c, K, (96, 96))
        loss = (out.color - target).abs().mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
    params = tuple(t.detach() for t in (means, quats, log_s.exp(), lo.sigmoid(), lc.sigmoid()))
    return params, w2c, K, (96, 96)


def colorize_depth(depth: torch.Tensor, vmax: float) -> np.ndarray:
    import matplotlib

    d = (depth.clamp(0, vmax) / vmax).numpy()
    rgb = matplotlib.colormaps["turbo"](1 - d)[..., :3]
    rgb[depth.numpy() == 0] = 0
    return rgb


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="render_street.png")
    ap.add_argument("--frame", type=int, default=0)
    args = ap.parse_args()
    if (STREET / "scene.json").is_file():
        gaussians, w2c, K, size = street_gaussians(args.frame)
        vmax = 40.0
    else:
        print("shared data absent: fitting Gaussians to a photo instead")
        gaussians, w2c, K, size = photo_gaussians()
        vmax = 1.5
    with torch.no_grad():
        out = rasterize_gaussians(*gaussians, w2c, K, size)
    color = out.color[0].permute(1, 2, 0).clamp(0, 1).numpy()
    depth = colorize_depth(out.depth[0, 0], vmax)
    normals = (0.5 - 0.5 * out.normals[0].permute(1, 2, 0)).numpy() * (out.alpha[0, 0, ..., None].numpy() > 0)
    panel = np.concatenate([color, depth, normals], axis=1)
    Image.fromarray((panel * 255).round().astype(np.uint8)).save(args.out, optimize=True)
    print(f"{len(gaussians[0])} Gaussians, {int(out.visible.sum())} visible -> {args.out}")


if __name__ == "__main__":
    main()
