r"""Reconstruct one flagged instance by multi-view stereo (paper, Sec. 4.3, Fig. 2 and 4).

:func:`reconstruct_instance`, given the scene's :class:`~vadgs.train.vad.visibility.VisibilityIndex`
(:func:`~vadgs.train.vad.visibility.build_visibility_index`), a reference view and an instance
flagged by :func:`~vadgs.train.vad.incomplete.find_incomplete`:

1. takes the instance's voxels (their visibility sets are the candidate views) — or, when the
   instance has almost no voxels of its own (the LiDAR missed it), the voxels the z-buffer sees
   *through* it in the reference view, whose observers also look at the missing surface;
2. selects ``k`` supporting views with the diversity-aware k-clique
   (:func:`~vadgs.select.select_views`), in the object's frame for a moving object;
3. runs PatchMatch on the whole group (each member as reference against the others), on crops
   around the instance (small instances at up to ``max_upsample`` times the resolution),
   matching only inside the instance's masks (static instances only
   against static pixels, a moving object only against itself), initialised from rendered depth
   and normals when given;
4. keeps the pixels whose depth at least ``min_consistent_views`` other members confirm
   (forward–backward reprojection, relative depth), completes the textureless parts of static
   planar instances, and
5. fuses them into points with normals and colours, in the instance's frame (world, or the
   object's own frame), with :func:`vadgs.mvs.fuse_depth_maps` (one point per consistent pixel);
6. returns each member's consistent depth and normals at the scene's resolution as priors.

This module holds steps 1–3 (``_instance_frame``, ``_select_supports``, ``_match``, and
:func:`match_work`, the matching's cost) and :func:`reconstruct_instance`, which runs them all on
the device of the index; step 3's crops and matching scale live in :mod:`vadgs.train.vad.crops`
(:func:`~vadgs.train.vad.crops.crop_group`, :func:`~vadgs.train.vad.crops.match_scale`), steps 4–6
in :mod:`vadgs.train.vad.fusion` (:func:`~vadgs.train.vad.fusion.consistent_depth`,
:func:`~vadgs.train.vad.fusion.explained_pixels`, :func:`~vadgs.train.vad.fusion.fuse_points`,
:func:`~vadgs.train.vad.fusion.depth_priors`), the settings, :class:`ReconstructConfig`, in
:mod:`vadgs.train.vad.reconstruct_config`.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import replace
from typing import TYPE_CHECKING, NamedTuple

import torch

from vadgs.checks import checking
from vadgs.mvs.patchmatch import PatchMatchConfig, patchmatch
from vadgs.select.covisibility import Covisibility
from vadgs.select.selector import ViewSelection, select_views
from vadgs.train.vad import reconstruct_config
from vadgs.train.vad.crops import Crops, MatchedCrops, crop_group, render_maps, shift_K, to_scale
from vadgs.train.vad.fusion import consistent_depth, depth_priors, explained_pixels, fuse_points
from vadgs.train.vad.lengths import REFERENCE_DEPTH, scene_lengths

if TYPE_CHECKING:
    from vadgs.train.vad.reconstruct_config import ReconstructConfig
    from vadgs.train.vad.visibility import VisibilityIndex

__all__ = [
    "InstanceReconstruction",
    "ViewRender",
    "match_work",
    "reconstruct_instance",
]


class InstanceReconstruction(NamedTuple):
    """Result of :func:`reconstruct_instance`.

    Attributes:
        points: ``(P, 3)`` in the instance's frame (world, or the track's object frame).
        normals: ``(P, 3)`` unit normals in that frame.
        colors: ``(P, 3)`` RGB in [0, 1].
        spacing: ``(P,)`` pixel footprint of each point (metres per pixel at its depth).
        track: the track id when the instance moves (points in its frame), else None.
        views: the group: the reference first, then the supporting views.
        depth: per group member, ``(1, H, W)`` consistent MVS depth in its full image (0 elsewhere),
            usable as a depth prior.
        normal: per group member, ``(3, H, W)`` MVS normals (camera frame), zeros elsewhere.
        reason: ``"ok"`` or why nothing (or little) was reconstructed; `` (seen)`` is appended when
            the supporting views were selected on the views' voxel z-buffers
            (``ReconstructConfig.seen_supports``).
        work: the PatchMatch work done, in pixel-sweeps (:func:`match_work`; 0 when nothing was
            matched): a count that does not depend on the machine, for the event's budget.
        consistent: the group's consistent MVS pixels (at the matching scale): the points fusion
            makes of them before those the Gaussians already explain are left out and the rest
            thinned (``points`` is what remains; 0 when nothing was matched).
    """

    points: torch.Tensor
    normals: torch.Tensor
    colors: torch.Tensor
    spacing: torch.Tensor
    track: int | None
    views: list[int]
    depth: list[torch.Tensor]
    normal: list[torch.Tensor]
    reason: str
    work: float = 0.0
    consistent: int = 0


class ViewRender(NamedTuple):
    """What the reconstruction needs of a rendered view (no gradient; camera-frame normals).

    Attributes:
        depth: ``(1, H, W)`` expected z-depth.
        alpha: ``(1, H, W)`` accumulated opacity.
        normals: ``(3, H, W)`` camera-frame normals (zeros where nothing is rendered).
    """

    depth: torch.Tensor
    alpha: torch.Tensor
    normals: torch.Tensor


class _InstanceFrame(NamedTuple):
    """Step 1's result: where the instance is matched and which voxels stand for it."""

    covis: Covisibility
    voxels: torch.Tensor  # (M,) bool
    world_to_cam: torch.Tensor  # (V, 4, 4): world (static) or object frame (track) to each view
    allowed: torch.Tensor  # (V,) bool: views that may support


def _instance_frame(
    index: VisibilityIndex, ref: int, instance: int, track: int | None, cfg: ReconstructConfig
) -> _InstanceFrame | str:
    """Step 1: the instance's voxels (their visibility sets are the candidate views) and its frame.

    A moving object: all voxels of its own grid, in its frame, views where its pose is known. A
    static instance with almost no voxels of its own (the LiDAR missed it): the voxels the z-buffer
    sees *through* it in the reference view, whose observers also look at the missing surface.
    Returns the reason as a string when there is nothing to match.
    """
    inputs = index.inputs
    dev = index.cameras.K.device
    if track is not None:
        if track not in index.track_covis:
            return "no_lidar_on_track"
        covis = index.track_covis[track]
        valid = inputs.tracks[track].valid.to(dev)
        pos = torch.tensor([inputs.frame_position(v) for v in range(inputs.num_views)], device=dev)
        return _InstanceFrame(
            covis,
            torch.ones(covis.num_voxels, dtype=torch.bool, device=dev),
            index.object_cameras(track),
            index.allowed & valid[pos],
        )
    voxels = index.labels == instance
    count = int(voxels.sum())
    if count < cfg.min_instance_voxels:
        _, vidx = index.voxel_raster(ref)
        through = torch.unique(vidx[(index.instances(ref) == instance) & (vidx >= 0)])
        voxels = voxels.clone()
        voxels[through] = True
        count = int(voxels.sum())
    if count == 0:
        return "no_voxels"
    return _InstanceFrame(index.covis, voxels, index.cameras.world_to_cam, index.allowed)


def _select_supports(
    index: VisibilityIndex,
    ref: int,
    instance: int,
    track: int | None,
    frame: _InstanceFrame,
    cfg: ReconstructConfig,
    generator: torch.Generator | None,
) -> ViewSelection:
    """Step 2: the supporting views (``cfg.whole_supports``: among the views showing all of the instance).

    ``cfg.seen_supports``: an instance whose visibility sets give nothing to select from is selected
    again on what the views' voxel z-buffers show (:meth:`VisibilityIndex.seen_covis`; a moving
    object's grid in its own frame, at each view's timestamp). A reference that shows fewer of its
    voxels than ``selection.min_shared`` (a far cell of the ground grid seen through one voxel)
    then asks its supports to share all it shows. The reason ends in ``" (seen)"`` when the
    z-buffers were used: the selection's on them when the reference shows any voxel there, else
    the visibility sets'.
    """
    sel = _select_among(index, ref, instance, frame.covis.restrict(frame.voxels), frame, cfg, generator)
    if not (cfg.seen_supports and sel.reason.startswith(("no_voxels", "no_candidates", "narrow_baselines"))):
        return sel
    views = [ref, *torch.nonzero(frame.allowed).flatten().tolist()]
    covis = index.seen_covis(frame.voxels, views, track)
    shown = len(covis.voxels_of(ref))
    if not shown:
        return sel
    if shown < cfg.selection.min_shared:
        cfg = replace(cfg, selection=replace(cfg.selection, min_shared=shown))
    seen = _select_among(index, ref, instance, covis, frame, cfg, generator)
    return replace(seen, reason=f"{seen.reason} (seen)")


def _select_among(
    index: VisibilityIndex,
    ref: int,
    instance: int,
    covis: Covisibility,
    frame: _InstanceFrame,
    cfg: ReconstructConfig,
    generator: torch.Generator | None,
) -> ViewSelection:
    """:func:`select_views` on ``covis``, among the views showing the whole instance when it can."""
    focal = float(index.cameras.K[ref, 0, 0]) if cfg.selection.min_parallax else None  # one read
    if cfg.whole_supports:
        allowed = frame.allowed.tolist()  # one read, and one for the border tests
        views = [v for v, a in enumerate(allowed) if a]
        cuts = index.cut_by_border_views([ref, *views], instance)
        if not cuts[0]:  # the reference shows the whole instance
            for v, cut in zip(views, cuts[1:]):
                allowed[v] = allowed[v] and not cut
            if sum(allowed) > cfg.selection.k:  # the reference is one of them
                whole = torch.tensor(allowed, dtype=torch.bool, device=frame.allowed.device)
                sel = select_views(ref, covis, cfg.selection, generator, whole, focal)
                if len(sel.views) == cfg.selection.k:
                    return sel
    return select_views(ref, covis, cfg.selection, generator, frame.allowed, focal)


def _depth_range(
    frame: _InstanceFrame, w2c_ref: torch.Tensor, cfg: ReconstructConfig, lengths: dict
) -> tuple[float, float]:
    """PatchMatch's depth range from the instance's voxels as the reference sees them."""
    cen = frame.covis.voxel_centers[frame.voxels]
    z = cen @ w2c_ref[2, :3] + w2c_ref[2, 3]
    front = z > lengths["min_voxel_depth"]
    inf = torch.full_like(z, math.inf)
    n, z_min, z_max = 0, 0.0, 0.0
    if z.numel():
        n, z_min, z_max = torch.stack(
            [
                front.sum().double(),
                torch.where(front, z, inf).min().double(),
                torch.where(front, z, -inf).max().double(),
            ]
        ).tolist()  # one read
    near, far = cfg.depth_margin
    lo, hi = (z_min * near, z_max * far) if n else lengths["fallback_depth_range"]
    lo = max(lo, lengths["min_depth"])
    return lo, max(hi, lo * 4, lengths["min_depth_span"])


def _match(
    index: VisibilityIndex,
    crops: Crops,
    group: list[int],
    world_to_cam: torch.Tensor,
    depth_range: tuple[float, float],
    cfg: ReconstructConfig,
    render_prior: Callable[[int], ViewRender] | None,
) -> MatchedCrops:
    """Step 3b: PatchMatch on the group, each member's crop as reference against all other views."""
    ch, cw = crops.size
    dev = crops.images.device
    ref_imgs, ref_masks, ref_K, init_d, init_n = [], [], [], [], []
    for i, (y0, x0) in zip(crops.members, crops.corners):
        ref_imgs.append(crops.images[i, :, y0 : y0 + ch, x0 : x0 + cw])
        ref_masks.append(crops.masks[i][None, y0 : y0 + ch, x0 : x0 + cw])
        ref_K.append(shift_K(crops.K[i], x0, y0))
        if render_prior is not None:
            d, _, n = render_maps(render_prior, group[i], index)
            d, n = d.to(dev), n.to(dev)
            known = d > 0
            d, n = to_scale(d, known, crops.scale), to_scale(n, known, crops.scale, unit=True)
            init_d.append(d[:, y0 : y0 + ch, x0 : x0 + cw])
            init_n.append(n[:, y0 : y0 + ch, x0 : x0 + cw])
    others = [[j for j in range(len(group)) if j != i] for i in crops.members]
    res = patchmatch(
        torch.stack(ref_imgs),
        torch.stack([crops.images[o] for o in others]),
        torch.stack(ref_K),
        torch.stack([crops.K[o] for o in others]),
        world_to_cam[crops.members],
        torch.stack([world_to_cam[o] for o in others]),
        depth_range,
        cfg.patchmatch,
        init_depth=torch.stack(init_d) if init_d else None,
        init_normal=torch.stack(init_n) if init_n else None,
        mask=torch.stack(ref_masks),
        src_masks=torch.stack([crops.regions[o] for o in others]),
    )
    return MatchedCrops(
        res, torch.stack(ref_imgs), torch.stack(ref_masks), torch.stack(ref_K), world_to_cam[crops.members]
    )


def match_work(masks: torch.Tensor, sources: int, config: PatchMatchConfig) -> float:
    """PatchMatch's work on the given reference masks, in pixel-sweeps (machine-independent).

    Reference pixels scored (the ``True`` pixels of ``masks``, at the matching scale) × source
    views × sweeps, a sweep at a pyramid level ``l`` levels coarser counting ``4^-l`` of one at the
    matching scale: ``iterations`` at the coarsest level and ``fine_iterations`` at each finer one
    (:class:`~vadgs.mvs.PatchMatchConfig`). An exact function of the crops (no timing): the unit of
    the VAD-GS event's ``work_budget``.

    Example:
        >>> from vadgs.mvs import PatchMatchConfig
        >>> m = torch.ones(1, 1, 10, 20, dtype=torch.bool)  # 200 pixels, 4 sources
        >>> match_work(m, 4, PatchMatchConfig(iterations=3, pyramid_levels=2, fine_iterations=1))
        1400.0
    """
    levels = max(int(config.pyramid_levels), 1)
    sweeps = config.iterations * 4.0 ** -(levels - 1)
    sweeps += config.fine_iterations * sum(4.0**-k for k in range(levels - 1))
    return float(masks.sum()) * sources * sweeps


@torch.no_grad()
def reconstruct_instance(
    index: VisibilityIndex,
    ref: int,
    instance: int,
    config: ReconstructConfig | None = None,
    generator: torch.Generator | None = None,
    render_prior: Callable[[int], ViewRender] | None = None,
    occupied: torch.Tensor | None = None,
    device: torch.device | str | None = None,
) -> InstanceReconstruction:
    """Reconstruct an instance seen in view ``ref`` from selected supporting views by PatchMatch.

    Not differentiable (a search). The steps (see the module docstring): the instance's voxels and
    frame, view selection (:func:`~vadgs.select.select_views`), crops at the instance's matching
    scale (:func:`~vadgs.train.vad.crops.match_scale`), PatchMatch (:func:`~vadgs.mvs.patchmatch`),
    consistency (:func:`~vadgs.mvs.geometric_consistency`) and planar completion
    (:func:`~vadgs.mvs.complete_planar`), the pixels the Gaussians already explain, fusion
    (:func:`~vadgs.mvs.fuse_depth_maps`, one point per consistent unexplained pixel, thinned to one
    per cell of the point spacing by :func:`~vadgs.train.vad.fusion.thin_points`), depth priors.

    Args:
        index: the scene's :class:`~vadgs.train.vad.visibility.VisibilityIndex`.
        ref: the reference view.
        instance: the instance id (a track id for a moving object: matched in its own frame).
        config: :class:`~vadgs.train.vad.reconstruct_config.ReconstructConfig`.
        generator: seeds the selection noise ``ξ`` (a CPU generator).
        render_prior: optional ``view -> ViewRender`` rendered by the Gaussians (camera-frame
            normals), the PatchMatch initialisation and the test of what is already explained;
            ``0`` where unknown. A function returning ``(depth, normal)`` initialises only.
        occupied: optional ``(Q, 3)`` points in the instance's frame (e.g. added earlier in the same
            event) whose cells take no new point.
        device: where the matching runs and the results are (default: the render prior's device
            when given, else the index's). Only the group's images, masks and cameras move there;
            the visibility index stays where it is.

    Returns:
        :class:`InstanceReconstruction` (possibly empty, with the reason).

    The arguments are checked here; the steps run with value checks off
    (:func:`vadgs.checks.checking`), on tensors built from the index's.
    """
    cfg = config or reconstruct_config.ReconstructConfig()
    unit = index.scene_depth / REFERENCE_DEPTH  # the lengths follow the scene (scene_lengths)
    lengths = scene_lengths(
        index.scene_depth, fallback_depth_range=cfg.fallback_depth_range, min_depth=cfg.min_depth
    )
    cfg = replace(cfg, selection=replace(cfg.selection, eps=cfg.selection.eps * unit))
    inputs = index.inputs
    if not 0 <= ref < inputs.num_views:
        raise ValueError(f"ref: expected a view in [0, {inputs.num_views}), got {ref}")
    track = instance if instance in inputs.tracks else None
    if device is None and render_prior is not None:
        device = render_maps(render_prior, ref)[0].device
    dev = torch.device(device) if device is not None else index.cameras.K.device
    empty3 = torch.zeros(0, 3, device=dev)

    def nothing(reason: str, views: list[int] | None = None) -> InstanceReconstruction:
        return InstanceReconstruction(
            empty3, empty3, empty3, torch.zeros(0, device=dev), track, views or [ref], [], [], reason
        )

    # The steps re-validate nothing: their tensors are built here from the index's (checked when
    # it was built) and the arguments above; a value check reads the device (a host sync on a GPU).
    with checking(False):
        if int((index.instances(ref) == instance).sum()) < cfg.min_pixels:
            return nothing("instance_too_small_in_reference")
        frame = _instance_frame(index, ref, instance, track, cfg)  # 1. voxels and frame
        if isinstance(frame, str):
            return nothing(frame)
        sel = _select_supports(index, ref, instance, track, frame, cfg, generator)  # 2.
        group = [ref, *sel.views.tolist()]
        if len(group) < 2:
            return nothing(f"selection:{sel.reason}")
        crops = crop_group(index, group, instance, track, cfg, dev)  # 3. crops and PatchMatch
        if isinstance(crops, str):
            return nothing(crops, group)
        w2c = frame.world_to_cam[group]
        depth_range = _depth_range(frame, w2c[0], cfg, lengths)
        w2c = w2c.to(dev)
        matched = _match(index, crops, group, w2c, depth_range, cfg, render_prior)
        work = match_work(matched.masks, len(group) - 1, cfg.patchmatch)
        planar = cfg.planar is not None and track is None  # a car is not planar
        cons = consistent_depth(matched, crops, group, w2c, planar, cfg, generator)  # 4.
        # 5. the unexplained pixels
        new = cons.keep & ~explained_pixels(index, cons, crops, group, cfg, render_prior)
        points, normals, colors, spacing = fuse_points(
            index, cons, matched, crops, new, track, cfg, occupied, generator, dev
        )  # one point per such pixel, in the instance's frame, thinned
        full_depth, full_normal = depth_priors(cons, crops, index.cameras.image_size)  # 6.
        views = [group[i] for i in crops.members]
        consistent = int(cons.keep.sum())
        reason = "ok" if points.shape[0] else ("explained" if consistent else "no_consistent_pixels")
        reason += " (seen)" if sel.reason.endswith("(seen)") else ""  # selected on the z-buffers
        return InstanceReconstruction(
            points, normals, colors, spacing, track, views, full_depth, full_normal, reason, work,
            consistent,
        )  # fmt: skip
