"""Naive, obviously-correct references for the geometry tests (loops; tiny inputs only)."""

from __future__ import annotations

import numpy as np
import torch


def slab_entry(origin: np.ndarray, direction: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> float | None:
    """Entry parameter ``t`` of the ray ``origin + t * direction`` into the box ``[lo, hi]``, or None."""
    t_in, t_out = -np.inf, np.inf
    for k in range(3):
        if direction[k] == 0.0:
            if not lo[k] <= origin[k] <= hi[k]:
                return None
            continue
        t1, t2 = (lo[k] - origin[k]) / direction[k], (hi[k] - origin[k]) / direction[k]
        t_in, t_out = max(t_in, min(t1, t2)), min(t_out, max(t1, t2))
    return t_in if t_in <= t_out and t_out > 0 else None


def naive_zbuffer(
    centers: torch.Tensor, voxel_size: float, K: torch.Tensor, world_to_cam: torch.Tensor, size, near=0.1
) -> tuple[np.ndarray, np.ndarray]:
    """Box-mode z-buffer by looping over pixels and voxels (float64): ``(depth (H, W), index (H, W))``.

    The ray of pixel ``(u, v)`` is ``o + t R^T K^-1 (u, v, 1)``, so ``t`` is the z-depth. Voxels
    with a corner closer than ``near`` are skipped, as :func:`vadgs.geometry.rasterize_voxels` does.
    """
    h, w = size
    c = centers.double().numpy()
    K = K.double().numpy()
    T = world_to_cam.double().numpy()
    rot, trans = T[:3, :3], T[:3, 3]
    origin = -rot.T @ trans
    half = voxel_size / 2
    corner_z = (c @ rot.T + trans)[:, 2] - half * np.abs(rot[2]).sum()
    kinv = np.linalg.inv(K)
    depth = np.zeros((h, w))
    index = np.full((h, w), -1, dtype=np.int64)
    for v in range(h):
        for u in range(w):
            d = rot.T @ kinv @ np.array([u, v, 1.0])
            best = (np.inf, -1)
            for m in range(len(c)):
                if corner_z[m] <= near:
                    continue
                t = slab_entry(origin, d, c[m] - half, c[m] + half)
                if t is not None and (t, m) < best:
                    best = (t, m)
            if best[1] >= 0:
                depth[v, u], index[v, u] = best
    return depth, index


def box_mesh(centers: np.ndarray, voxel_size: float):
    """One trimesh of axis-aligned boxes; face ``f`` belongs to box ``f // 12``."""
    import trimesh

    unit = trimesh.creation.box(extents=(voxel_size,) * 3)
    nv, nf = len(unit.vertices), len(unit.faces)
    verts = (centers[:, None, :] + unit.vertices[None]).reshape(-1, 3)
    faces = (unit.faces[None] + nv * np.arange(len(centers))[:, None, None]).reshape(-1, 3)
    assert nf == 12
    return trimesh.Trimesh(verts, faces, process=False)


def embree_zbuffer(mesh, K: torch.Tensor, world_to_cam: torch.Tensor, size) -> tuple[np.ndarray, np.ndarray]:
    """Ray cast a box mesh with Embree: z-depth and box id of the first hit per pixel."""
    from trimesh.ray.ray_pyembree import RayMeshIntersector

    h, w = size
    K = K.double().numpy()
    T = world_to_cam.double().numpy()
    rot, trans = T[:3, :3], T[:3, 3]
    origin = -rot.T @ trans
    vs, us = np.mgrid[0:h, 0:w]
    pix = np.stack([us.ravel(), vs.ravel(), np.ones(h * w)], 1)
    dirs = pix @ (rot.T @ np.linalg.inv(K)).T
    caster = RayMeshIntersector(mesh)
    loc, ray, tri = caster.intersects_location(np.broadcast_to(origin, dirs.shape), dirs, multiple_hits=False)
    depth = np.zeros(h * w)
    index = np.full(h * w, -1, dtype=np.int64)
    depth[ray] = loc @ rot[2] + trans[2]
    index[ray] = tri // 12
    return depth.reshape(h, w), index.reshape(h, w)
