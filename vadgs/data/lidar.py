"""Accumulate a scene's LiDAR over frames, with the observation table that voxel visibility needs."""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from typing import NamedTuple

import torch

from vadgs.data.scene import Scene
from vadgs.geometry.camera import invert_rigid, observing_views

__all__ = ["AccumulatedLidar", "accumulate_lidar", "iter_lidar", "lidar_depth_map"]


class AccumulatedLidar(NamedTuple):
    """LiDAR points of several frames.

    Attributes:
        points: ``(N, 3)`` points (world frame, or the object's frame for a track).
        instance: ``(N,)`` int64 instance ids.
        frame: ``(N,)`` int64 frame index each point comes from.
        point_views: COO observation table ``(point_idx (P,), view_idx (P,))``: the cameras of
            each point's own frame that see it (in front, inside the image).
    """

    points: torch.Tensor
    instance: torch.Tensor
    frame: torch.Tensor
    point_views: tuple[torch.Tensor, torch.Tensor]


def accumulate_lidar(
    scene: Scene,
    frames: Sequence[int] | None = None,
    exclude_dynamic: bool = True,
    track_id: int | None = None,
) -> AccumulatedLidar:
    """Accumulate LiDAR over frames with each point's observing views.

    All frames' points at once; :func:`iter_lidar` gives them frame by frame (a segment's
    30 million points need not be held together).

    Args:
        scene: the scene.
        frames: frame indices (default: the training frames, or all frames if there is no split).
        exclude_dynamic: drop the points of moving objects (instance ids of ``scene.tracks``),
            which would smear across the world frame.
        track_id: keep only the points of this moving object, moved into its own frame
            (``object_to_world[f]^-1 @ p`` per frame ``f``); overrides ``exclude_dynamic``.

    Returns:
        :class:`AccumulatedLidar`. Feed ``points`` and ``point_views`` to
        :func:`vadgs.geometry.voxelize` with ``num_views=scene.num_views``.

    Example:
        >>> from vadgs.data import load_scene, sample_scene_path
        >>> scene = load_scene(sample_scene_path())
        >>> acc = accumulate_lidar(scene)
        >>> acc.points.shape[1], bool((acc.frame.unique() == torch.tensor(scene.train_frames)).all())
        (3, True)
    """
    pts, ins, frm, pv_p, pv_v = [], [], [], [], []
    offset = 0
    for sweep in iter_lidar(scene, frames, exclude_dynamic, track_id):
        pts.append(sweep.points)
        ins.append(sweep.instance)
        frm.append(sweep.frame)
        pv_p.append(sweep.point_views[0] + offset)
        pv_v.append(sweep.point_views[1])
        offset += sweep.points.shape[0]
    empty = torch.zeros(0, dtype=torch.int64)
    return AccumulatedLidar(
        torch.cat(pts) if pts else torch.zeros(0, 3),
        torch.cat(ins) if ins else empty,
        torch.cat(frm) if frm else empty,
        (torch.cat(pv_p) if pv_p else empty, torch.cat(pv_v) if pv_v else empty),
    )


def iter_lidar(
    scene: Scene,
    frames: Sequence[int] | None = None,
    exclude_dynamic: bool = True,
    track_id: int | None = None,
    views: bool = True,
) -> Iterator[AccumulatedLidar]:
    """:func:`accumulate_lidar` one frame at a time: each frame's sweep is read when it is reached.

    Yields one :class:`AccumulatedLidar` per frame (in ``frames``' order), its ``point_views``
    numbering the frame's own points; ``views=False`` leaves them empty (the costly part, when
    only the points are needed). Arguments as :func:`accumulate_lidar`.

    Example:
        >>> from vadgs.data import load_scene, sample_scene_path
        >>> scene = load_scene(sample_scene_path())
        >>> sweeps = list(iter_lidar(scene))
        >>> n = sum(len(s.points) for s in sweeps)
        >>> len(sweeps) == len(scene.train_frames), n == len(accumulate_lidar(scene).points)
        (True, True)
    """
    if frames is None:
        frames = scene.train_frames or [f.index for f in scene.frames]
    if track_id is not None and track_id not in scene.tracks:
        raise ValueError(
            f"track_id: {track_id} is not a track of scene {scene.name!r} ({list(scene.tracks)})"
        )
    dynamic = torch.tensor(sorted(scene.tracks), dtype=torch.int64)
    empty = torch.zeros(0, dtype=torch.int64)
    for f in frames:
        lid = scene.lidar(f)
        p, i = lid.points, lid.instance
        if track_id is not None:
            fpos = scene.frame_position(f)
            keep = i == track_id
            if not bool(scene.tracks[track_id].valid[fpos]):
                keep &= False
        elif exclude_dynamic and dynamic.numel():
            keep = ~torch.isin(i, dynamic)
        else:
            keep = torch.ones_like(i, dtype=torch.bool)
        p, i = p[keep], i[keep]
        view_ids = list(scene.frames[scene.frame_position(f)].view_ids)
        pv_p, pv_v = [], []
        if views and p.shape[0] and view_ids:
            for ids in scene.size_groups(view_ids):  # cameras of one image size at a time
                pi, vi = observing_views(p, scene.cameras(ids), ids)
                pv_p.append(pi)
                pv_v.append(vi)
        if track_id is not None and p.shape[0]:
            o2w = scene.tracks[track_id].object_to_world[scene.frame_position(f)]
            w2o = invert_rigid(o2w)
            p = p @ w2o[:3, :3].T + w2o[:3, 3]
        yield AccumulatedLidar(
            p,
            i,
            torch.full((p.shape[0],), f, dtype=torch.int64),
            (torch.cat(pv_p) if pv_p else empty, torch.cat(pv_v) if pv_v else empty),
        )


def lidar_depth_map(scene: Scene, view: int) -> torch.Tensor:
    """The view's own LiDAR sweep projected into it: ``(1, 1, H, W)`` nearest z per pixel, 0 elsewhere.

    Example:
        >>> from vadgs.data import load_scene, sample_scene_path
        >>> scene = load_scene(sample_scene_path())
        >>> d = lidar_depth_map(scene, 0)
        >>> d.shape, bool((d > 0).any())
        (torch.Size([1, 1, 144, 240]), True)
    """
    from vadgs.geometry.camera import project_points

    v = scene.views[view]
    cams = scene.cameras([view])
    h, w = cams.image_size
    pts = scene.lidar(v.frame).points
    uv, z = project_points(pts[None], cams.K, cams.world_to_cam)
    u, vv = uv[0, :, 0].round().long(), uv[0, :, 1].round().long()
    ok = (z[0] > 0.1) & (u >= 0) & (u < w) & (vv >= 0) & (vv < h)
    flat = vv[ok] * w + u[ok]
    depth = torch.full((h * w,), float("inf"))
    depth.scatter_reduce_(0, flat, z[0][ok], reduce="amin")
    depth[torch.isinf(depth)] = 0.0
    return depth.reshape(1, 1, h, w)
