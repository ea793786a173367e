"""Naive, obviously-correct references for the renderer tests (loops over pixels and Gaussians)."""

from __future__ import annotations

import math

import torch


def quat_to_rot(q: torch.Tensor) -> torch.Tensor:
    q = q / q.norm()
    w, x, y, z = q
    return torch.stack(
        [
            torch.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)]),
            torch.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)]),
            torch.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]),
        ]
    )


def project_naive(
    means, quats, scales, opacities, world_to_cam, K, image_size, near, far, eps2d, antialiased
):
    """One camera, one Gaussian at a time: list of dicts (None where culled)."""
    h, w = image_size
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    W, t = world_to_cam[:3, :3], world_to_cam[:3, 3]
    out = []
    for i in range(means.shape[0]):
        p = W @ means[i] + t
        if not near < float(p[2].detach()) < far:
            out.append(None)
            continue
        R = quat_to_rot(quats[i])
        sigma = R @ torch.diag(scales[i] ** 2) @ R.T
        x, y, z = p
        # gsplat's clamp of the ray, pixel centres at integers -> image spans [-0.5, W - 0.5]
        lim_xp = (w - (cx + 0.5)) / fx + 0.3 * (0.5 * w / fx)
        lim_xn = (cx + 0.5) / fx + 0.3 * (0.5 * w / fx)
        lim_yp = (h - (cy + 0.5)) / fy + 0.3 * (0.5 * h / fy)
        lim_yn = (cy + 0.5) / fy + 0.3 * (0.5 * h / fy)
        tx = z * torch.clamp(x / z, -lim_xn, lim_xp)
        ty = z * torch.clamp(y / z, -lim_yn, lim_yp)
        J = torch.stack(
            [
                torch.stack([fx / z, torch.zeros_like(z), -fx * tx / z**2]),
                torch.stack([torch.zeros_like(z), fy / z, -fy * ty / z**2]),
            ]
        )
        cov = J @ W @ sigma @ W.T @ J.T
        det_raw = torch.linalg.det(cov)
        cov = cov + eps2d * torch.eye(2, dtype=cov.dtype)
        opac = opacities[i]
        if antialiased:
            opac = opac * torch.sqrt(torch.clamp_min(det_raw / torch.linalg.det(cov), 0.0))
        n = W @ R[:, int(torch.argmin(scales[i]))]
        if float((n @ p).detach()) > 0:
            n = -n
        mean2d = torch.stack([fx * x / z + cx, fy * y / z + cy])
        out.append({"mean2d": mean2d, "conic": torch.linalg.inv(cov), "z": z, "opac": opac, "normal": n})
    return out


def render_naive(
    means,
    quats,
    scales,
    opacities,
    colors,
    world_to_cam,
    K,
    image_size,
    background=None,
    near=0.01,
    far=1e10,
    eps2d=0.3,
    antialiased=False,
    alpha_max=0.999,
    alpha_min=1.0 / 255.0,
    t_min=1e-4,
):
    """Render one camera pixel by pixel. Returns color (D,H,W), alpha, depth, median, normals (·,H,W)."""
    h, w = image_size
    gs = project_naive(
        means, quats, scales, opacities, world_to_cam, K, image_size, near, far, eps2d, antialiased
    )
    order = sorted((i for i, g in enumerate(gs) if g is not None), key=lambda i: float(gs[i]["z"].detach()))
    d = colors.shape[1]
    pix_color, pix_alpha, pix_depth, pix_median, pix_normal = [], [], [], [], []
    zero = means.new_zeros(())
    for v in range(h):
        for u in range(w):
            T = means.new_ones(())
            c = means.new_zeros(d)
            dep = zero
            nrm = means.new_zeros(3)
            median = zero
            for i in order:
                g = gs[i]
                dx = torch.stack([g["mean2d"][0] - u, g["mean2d"][1] - v])
                sigma = 0.5 * dx @ g["conic"] @ dx
                alpha = torch.clamp_max(g["opac"] * torch.exp(-sigma), alpha_max)
                if float(sigma.detach()) < 0 or float(alpha.detach()) < alpha_min:
                    continue
                next_T = T * (1 - alpha)
                if float(next_T.detach()) <= t_min:
                    break
                wgt = alpha * T
                c = c + wgt * colors[i]
                dep = dep + wgt * g["z"]
                nrm = nrm + wgt * g["normal"]
                if float(T.detach()) > 0.5 >= float(next_T.detach()):
                    median = g["z"]
                T = next_T
            acc = 1 - T
            if background is not None:
                c = c + T * background
            pix_color.append(c)
            pix_alpha.append(acc)
            pix_depth.append(dep / acc if float(acc.detach()) > 0 else zero)
            pix_median.append(median)
            nn_ = nrm.norm()
            pix_normal.append(nrm / nn_ if float(nn_.detach()) > 0 else nrm)
    color = torch.stack(pix_color, -1).reshape(d, h, w)
    alpha = torch.stack(pix_alpha).reshape(1, h, w)
    depth = torch.stack(pix_depth).reshape(1, h, w)
    median = torch.stack(pix_median).reshape(1, h, w)
    normals = torch.stack(pix_normal, -1).reshape(3, h, w)
    return color, alpha, depth, median, normals


def random_scene(n, image_size, seed=0, dtype=torch.float32, opac=(0.2, 0.95), scale=(0.02, 0.25), batch=1):
    """Random Gaussians in front of a few cameras looking at the origin from z = -4."""
    g = torch.Generator().manual_seed(seed)
    h, w = image_size
    means = (torch.rand(n, 3, generator=g, dtype=dtype) * 2 - 1) * torch.tensor([1.2, 1.0, 1.0], dtype=dtype)
    quats = torch.randn(n, 4, generator=g, dtype=dtype)
    lo, hi = math.log(scale[0]), math.log(scale[1])
    scales = torch.exp(torch.rand(n, 3, generator=g, dtype=dtype) * (hi - lo) + lo)
    opacities = torch.rand(n, generator=g, dtype=dtype) * (opac[1] - opac[0]) + opac[0]
    colors = torch.rand(n, 3, generator=g, dtype=dtype)
    f = 0.9 * w
    K = torch.tensor([[f, 0, (w - 1) / 2], [0, f, (h - 1) / 2], [0, 0, 1]], dtype=dtype).expand(batch, 3, 3)
    w2c = torch.eye(4, dtype=dtype).repeat(batch, 1, 1)
    w2c[:, 2, 3] = 4.0
    for b in range(1, batch):  # small rotation about y for the other cameras
        a = 0.15 * b
        w2c[b, :3, :3] = torch.tensor(
            [[math.cos(a), 0, math.sin(a)], [0, 1, 0], [-math.sin(a), 0, math.cos(a)]], dtype=dtype
        )
    return means, quats, scales, opacities, colors, w2c.contiguous(), K.contiguous()
