"""Instance maps painted from 3D boxes, for recordings that have boxes but no segmentation.

PSNR* (:mod:`vadgs.train.results.evaluate`) is measured on the pixels of moving objects, which
it reads from the test views' instance maps. A converted driving log (PandaSet, nuScenes, Waymo)
has 3D boxes but no per-pixel masks: :func:`box_instance_map` paints each track's box into a view
(every pixel whose ray enters the box, exact ray–box intersection; the nearest box wins), and
:func:`~vadgs.data.export_scene` writes them with ``box_masks=True``.

A box is larger than the object it bounds (wheels, mirrors, a car's rounded corners), so the mask
covers some background around each vehicle, and a static object in front of a box does not hide it.
"""

from __future__ import annotations

import torch

from vadgs.data.scene import Scene

__all__ = ["box_instance_map", "ray_box_entry"]


def ray_box_entry(origins: torch.Tensor, directions: torch.Tensor, half_size: torch.Tensor) -> torch.Tensor:
    """Ray parameter where each ray enters a centred axis-aligned box (slab method); inf on a miss.

    Not differentiable (a geometric test).

    Args:
        origins: ``(3,)`` ray origin in the box frame.
        directions: ``(N, 3)`` ray directions in the box frame.
        half_size: ``(3,)`` half extents.

    Returns:
        ``(N,)`` the smallest ``t >= 0`` with ``origin + t * direction`` in the box (0 when the
        origin is inside), ``inf`` for rays that miss it.

    Example:
        >>> d = torch.tensor([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
        >>> ray_box_entry(torch.tensor([-5.0, 0.0, 0.0]), d, torch.ones(3)).tolist()
        [4.0, inf]
    """
    inv = 1.0 / directions  # ±inf for a zero component: the slab test still holds
    t1 = (-half_size - origins) * inv
    t2 = (half_size - origins) * inv
    lo = torch.minimum(t1, t2)
    hi = torch.maximum(t1, t2)
    # a ray parallel to a slab: inside it (nan from 0 * inf) never limits, outside it always misses
    parallel = directions == 0
    outside = parallel & ((origins.abs() > half_size).expand_as(parallel))
    lo = torch.where(parallel, torch.where(outside, torch.inf, -torch.inf), lo)
    hi = torch.where(parallel, torch.where(outside, -torch.inf, torch.inf), hi)
    t_in = lo.amax(-1).clamp(min=0.0)
    t_out = hi.amin(-1)
    return torch.where(t_in <= t_out, t_in, torch.full_like(t_in, torch.inf))


def box_instance_map(scene: Scene, view: int) -> torch.Tensor:
    """The instance map of a view painted from the boxes of the scene's tracks at the view's frame.

    Each pixel centre's ray (through ``K`` and ``cam_to_world``, at the scene's resolution) takes
    the id of the nearest track box it enters, 0 when it enters none. Only tracks (the moving
    rigid objects, ``Track.size_lwh`` about ``object_to_world``) are painted.

    Args:
        scene: the scene.
        view: the view's index.

    Returns:
        ``(H, W)`` int64 instance ids (0 = none).

    Example:
        >>> from vadgs.data import load_scene, sample_scene_path
        >>> scene = load_scene(sample_scene_path())
        >>> m = box_instance_map(scene, scene.test_views[0])
        >>> tuple(m.shape), set(m.unique().tolist()) <= {0, *scene.tracks}
        ((144, 240), True)
    """
    v = scene.views[view]
    h, w = scene.image_size(view)
    K = scene.cameras_info[v.camera].K.double()
    c2w = v.cam_to_world.double()
    pos = scene.view_frame_position(view)
    ys, xs = torch.meshgrid(
        torch.arange(h, dtype=torch.float64), torch.arange(w, dtype=torch.float64), indexing="ij"
    )
    pix = torch.stack([xs.reshape(-1), ys.reshape(-1), torch.ones(h * w, dtype=torch.float64)], -1)
    rays_cam = pix @ torch.linalg.inv(K).T  # z = 1: the ray parameter is the z-depth
    rays_world = rays_cam @ c2w[:3, :3].T
    best = torch.full((h * w,), torch.inf, dtype=torch.float64)
    out = torch.zeros(h * w, dtype=torch.int64)
    for tid, track in sorted(scene.tracks.items()):
        if not bool(track.valid[pos]):
            continue
        o2w = track.object_to_world[pos].double()
        R, t = o2w[:3, :3], o2w[:3, 3]
        origin = R.T @ (c2w[:3, 3] - t)
        depth = ray_box_entry(origin, rays_world @ R, track.size_lwh.double() / 2)
        nearer = depth < best
        best = torch.where(nearer, depth, best)
        out[nearer] = tid
    return out.reshape(h, w)
