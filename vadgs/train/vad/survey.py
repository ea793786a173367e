"""Step 1 of :func:`~vadgs.train.vad.reconstruct.reconstruct_instance`: an instance's voxels and frame.

:func:`instance_frame` gives the voxels that stand for an instance in a reference view and the
frame it is matched in (the world, or a moving object's own); :func:`survey_instance` reads, once
per instance, what planning needs of it in all its pairs (:class:`InstanceSurvey`: its frame, the
views that may support it and those that cut it, its pixels and its voxels' depths in its
candidate references), and :func:`reference_frame` gives one pair's frame and depths from it.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import TYPE_CHECKING, NamedTuple

import torch

from vadgs.checks import checking
from vadgs.select.covisibility import Covisibility
from vadgs.train.vad import reconstruct_config
from vadgs.train.vad.lengths import scene_lengths

if TYPE_CHECKING:
    from vadgs.train.vad.reconstruct_config import ReconstructConfig
    from vadgs.train.vad.visibility import VisibilityIndex

__all__ = ["InstanceFrame", "InstanceSurvey", "instance_frame", "reference_frame", "survey_instance"]


class InstanceFrame(NamedTuple):
    """Step 1's result (:func:`instance_frame`): where the instance is matched, which voxels stand for it.

    Attributes:
        covis: the voxels' visibility sets: the scene's static grid, or the track's own grid.
        voxels: ``(M,)`` bool: the voxels of ``covis`` that stand for the instance.
        world_to_cam: ``(V, 4, 4)``: from the instance's frame (the world for a static instance,
            the object's frame for a track) to each view's camera.
        allowed: ``(V,)`` bool: the views that may support (a track's: those where its pose is known).
    """

    covis: Covisibility
    voxels: torch.Tensor
    world_to_cam: torch.Tensor
    allowed: torch.Tensor


def instance_frame(
    index: VisibilityIndex, ref: int, instance: int, track: int | None, cfg: ReconstructConfig
) -> InstanceFrame | str:
    """Step 1: the instance's voxels (their visibility sets are the candidate views) and its frame.

    The paper (Sec. 4.3) treats a rigid moving vehicle as static "by transforming all observation
    views into its local coordinate system": a moving object (``track`` given) is matched in its
    object frame, on all voxels of its own grid, among the views where its pose is known
    (``world_to_cam`` = :meth:`~vadgs.train.vad.visibility.VisibilityIndex.object_cameras`). A
    static instance is matched in the world; with almost no voxels of its own (the LiDAR missed
    it), on the voxels the z-buffer sees *through* it in the reference view, whose observers also
    look at the missing surface.

    Args:
        index: the visibility index.
        ref: the reference view.
        instance: the instance's id in the instance maps.
        track: the instance's track id when it moves, else None.
        cfg: the settings (``min_instance_voxels``).

    Returns:
        :class:`InstanceFrame`, or the reason as a string when there is nothing to match
        (``"no_lidar_on_track"``, ``"no_voxels"``).
    """
    frame = _own_frame(index, instance, track)
    if track is not None or isinstance(frame, str):
        return frame
    voxels = frame.voxels
    count = int(voxels.sum())
    if count < cfg.min_instance_voxels:
        _, vidx = index.voxel_raster(ref)
        through = torch.unique(vidx[(index.instances(ref) == instance) & (vidx >= 0)])
        voxels = voxels.clone()
        voxels[through] = True
        count = int(voxels.sum())
    if count == 0:
        return "no_voxels"
    return frame._replace(voxels=voxels)


def _own_frame(index: VisibilityIndex, instance: int, track: int | None) -> InstanceFrame | str:
    """:func:`instance_frame` on the instance's own voxels (none added through it; no read)."""
    inputs = index.inputs
    dev = index.cameras.K.device
    if track is not None:
        if track not in index.track_covis:
            return "no_lidar_on_track"
        covis = index.track_covis[track]
        valid = inputs.tracks[track].valid.to(dev)
        pos = torch.tensor([inputs.frame_position(v) for v in range(inputs.num_views)], device=dev)
        return InstanceFrame(
            covis,
            torch.ones(covis.num_voxels, dtype=torch.bool, device=dev),
            index.object_cameras(track),
            index.allowed & valid[pos],
        )
    return InstanceFrame(index.covis, index.labels == instance, index.cameras.world_to_cam, index.allowed)


class InstanceSurvey(NamedTuple):
    """What planning needs of an instance in all its pairs, read at once (:func:`survey_instance`).

    Attributes:
        instance: the instance.
        track: its track id when it moves, else None.
        frame: its :class:`InstanceFrame` on its own voxels, or why there is none
            (``"no_lidar_on_track"``, ``"no_voxels"``).
        covis: ``frame.covis`` restricted to ``frame.voxels``; None when the instance has fewer
            than ``min_instance_voxels`` voxels of its own (each reference then adds those seen
            through it: :func:`instance_frame`, with its own reads).
        allowed: per view of the index, whether it may support (``frame.allowed``).
        cut: view → whether the instance touches the view's border
            (:meth:`~vadgs.train.vad.visibility.VisibilityIndex.cut_by_border`): the training views
            and the surveyed ones.
        pixels: surveyed view → the instance's pixels in it.
        depths: surveyed view → ``(n, near, far)``: how many of its own voxels lie in front of the
            view (beyond ``min_voxel_depth``) and the nearest's and farthest's depth.
    """

    instance: int
    track: int | None
    frame: InstanceFrame | str
    covis: Covisibility | None
    allowed: list[bool]
    cut: dict[int, bool]
    pixels: dict[int, int]
    depths: dict[int, tuple[float, float, float]]


@torch.no_grad()
def survey_instance(
    index: VisibilityIndex, instance: int, views: Sequence[int], config: ReconstructConfig | None = None
) -> InstanceSurvey:
    """An instance's :class:`InstanceSurvey` in ``views`` (its candidate references), in one host read.

    Its own voxels and frame, the views that may support it and those that cut it (for the
    whole-reference and whole-support rules), its pixels and its voxels' depths in each of
    ``views``: what :func:`~vadgs.train.vad.reconstruct.plan_matches` reads for each of its pairs otherwise.
    """
    cfg = config or reconstruct_config.ReconstructConfig()
    lengths = scene_lengths(
        index.scene_depth, fallback_depth_range=cfg.fallback_depth_range, min_depth=cfg.min_depth
    )
    inputs = index.inputs
    track = instance if instance in inputs.tracks else None
    views = list(dict.fromkeys(int(v) for v in views))
    for v in views:
        if not 0 <= v < inputs.num_views:
            raise ValueError(f"views: expected views in [0, {inputs.num_views}), got {v}")
    cut_views = sorted(set(inputs.train_views) | set(views))
    dev = index.cameras.K.device
    with checking(False):  # see reconstruct_instance
        frame = _own_frame(index, instance, track)
        parts = [index.border_cuts(cut_views, instance).to(dev)]
        parts += [(index.instances(v) == instance).sum()[None].to(dev) for v in views]
        if isinstance(frame, InstanceFrame):
            parts += [frame.allowed.to(dev), frame.covis.restrict_sizes(frame.voxels).to(dev)]
            parts += [_depth_stats(frame, frame.world_to_cam[v], lengths).to(dev) for v in views]
        host = torch.cat([p.double().flatten() for p in parts]).tolist()  # the one read
    cut = dict(zip(cut_views, map(bool, host[: len(cut_views)])))
    at = len(cut_views) + len(views)
    pixels = dict(zip(views, map(int, host[len(cut_views) : at])))
    if isinstance(frame, str):
        return InstanceSurvey(instance, track, frame, None, [], cut, pixels, {})
    num = inputs.num_views
    allowed = [bool(a) for a in host[at : at + num]]
    count, entries = int(host[at + num]), int(host[at + num + 1])
    stats = host[at + num + 2 :]
    depths = {v: (stats[3 * k], stats[3 * k + 1], stats[3 * k + 2]) for k, v in enumerate(views)}
    covis = None
    if track is not None or count >= cfg.min_instance_voxels:
        if count == 0 and track is None:  # (a track's grid is matched whatever it holds)
            return InstanceSurvey(instance, track, "no_voxels", None, allowed, cut, pixels, depths)
        with checking(False):
            covis = frame.covis.restrict(frame.voxels, sizes=(count, entries))
    return InstanceSurvey(instance, track, frame, covis, allowed, cut, pixels, depths)


def _depth_stats(frame: InstanceFrame, w2c_ref: torch.Tensor, lengths: dict) -> torch.Tensor:
    """``(3,)`` double on the device: ``(n, near, far)`` of the frame's voxels in front of a view.

    Every voxel's depth (no data-dependent selection: no read); ``±inf`` when there is none.
    """
    cen = frame.covis.voxel_centers
    w2c_ref = w2c_ref.to(cen.device)
    z = cen @ w2c_ref[2, :3] + w2c_ref[2, 3]
    front = frame.voxels & (z > lengths["min_voxel_depth"])
    inf = torch.full_like(z, math.inf)
    if not z.numel():
        return torch.tensor([0.0, math.inf, -math.inf], dtype=torch.float64, device=cen.device)
    return torch.stack(
        [
            front.sum().double(),
            torch.where(front, z, inf).min().double(),
            torch.where(front, z, -inf).max().double(),
        ]
    )


def reference_frame(
    index: VisibilityIndex, ref: int, survey: InstanceSurvey, config: ReconstructConfig
) -> tuple[InstanceFrame, tuple[float, float, float]] | str:
    """The frame of the instance's pair with reference ``ref``, and its voxels' depths there.

    The survey's own frame and depths (:attr:`InstanceSurvey.depths`, no read) when its own voxels
    stand for it; else those seen through it from ``ref`` join them (:func:`instance_frame`, with
    its reads). The reason as a string when there is nothing to match.
    """
    if isinstance(survey.frame, str):
        return survey.frame
    if survey.covis is not None:
        return survey.frame, survey.depths[ref]
    found = instance_frame(index, ref, survey.instance, survey.track, config)
    if isinstance(found, str):
        return found
    lengths = scene_lengths(
        index.scene_depth, fallback_depth_range=config.fallback_depth_range, min_depth=config.min_depth
    )
    n, lo, hi = _depth_stats(found, found.world_to_cam[ref], lengths).tolist()  # one read
    return found, (n, lo, hi)
