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

This module holds steps 2–3a (:func:`select_supports`, :func:`plan_matches`) and
:func:`reconstruct_instance`, which runs them all on the device of the index, in three parts that
an event runs over all its (instance, reference) pairs: :func:`plan_matches` (steps 1–3a, an
instance's pairs after one survey of it: a :class:`~vadgs.train.vad.matching.MatchPlan` each),
:func:`~vadgs.train.vad.matching.match_plans` (step 3b, every pair's PatchMatch in few batched
calls) and :func:`finish_match` (steps 4–6, pair by pair). Step 1, the instance's frame and its
survey, lives in :mod:`vadgs.train.vad.survey` (:func:`~vadgs.train.vad.survey.instance_frame`,
:func:`~vadgs.train.vad.survey.survey_instance`), step 3b in :mod:`vadgs.train.vad.matching`,
step 3's crops and matching scale in :mod:`vadgs.train.vad.crops`
(:func:`~vadgs.train.vad.crops.crop_group`, :func:`~vadgs.train.vad.crops.match_scale`), steps 4–6
in :mod:`vadgs.train.vad.fusion` (:func:`~vadgs.train.vad.fusion.consistent_depth`,
:func:`~vadgs.train.vad.fusion.explained_pixels`, :func:`~vadgs.train.vad.fusion.fuse_points`,
:func:`~vadgs.train.vad.fusion.depth_priors`), the settings, :class:`ReconstructConfig`, in
:mod:`vadgs.train.vad.reconstruct_config`.

Host reads: an instance's survey, each pair's view selection (one read,
:func:`~vadgs.select.select_views`) and crops, the plans' work together; the rest is computed on
the device and read where a size or a decision needs it.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import replace
from typing import TYPE_CHECKING, NamedTuple

import torch

from vadgs.checks import checking
from vadgs.select.covisibility import Covisibility
from vadgs.select.selector import ViewSelection, select_views
from vadgs.train.vad import reconstruct_config
from vadgs.train.vad.crops import MatchedCrops, crop_group, render_maps
from vadgs.train.vad.fusion import consistent_depth, depth_priors, explained_pixels, fuse_points, lidar_check
from vadgs.train.vad.lengths import REFERENCE_DEPTH, scene_lengths
from vadgs.train.vad.matching import MatchPlan, match_plans, match_work
from vadgs.train.vad.survey import InstanceFrame, InstanceSurvey, reference_frame, survey_instance

if TYPE_CHECKING:
    from vadgs.train.vad.reconstruct_config import ReconstructConfig
    from vadgs.train.vad.visibility import VisibilityIndex

__all__ = [
    "InstanceReconstruction",
    "ViewRender",
    "finish_match",
    "plan_matches",
    "reconstruct_instance",
    "select_supports",
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
        reason: ``"ok"`` or why nothing (or little) was reconstructed (``"lidar_disagrees"``: the
            members' own LiDAR contradicts most of the checked matches,
            ``ReconstructConfig.max_lidar_error``); `` (seen)`` is appended when the supporting views
            were selected on the views' voxel z-buffers (``ReconstructConfig.seen_supports``).
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


def select_supports(
    index: VisibilityIndex,
    ref: int,
    instance: int,
    track: int | None,
    frame: InstanceFrame,
    cfg: ReconstructConfig,
    generator: torch.Generator | None,
    survey: InstanceSurvey | None = None,
) -> ViewSelection:
    """Step 2: the supporting views (``cfg.whole_supports``: among the views showing all of the instance).

    ``cfg.seen_supports``: an instance whose visibility sets give nothing to select from is selected
    again on what the views' voxel z-buffers show (:meth:`VisibilityIndex.seen_covis`; a moving
    object's grid in its own frame, at each view's timestamp). A reference that shows fewer of its
    voxels than ``selection.min_shared`` (a far cell of the ground grid seen through one voxel)
    then asks its supports to share all it shows. The reason ends in ``" (seen)"`` when the
    z-buffers were used: the selection's on them when the reference shows any voxel there, else
    the visibility sets'. ``survey``: the instance's (its restricted visibility sets, the views
    allowed and those cut by the border: no read of them here).

    Args:
        index: the scene's visibility index.
        ref: the reference view.
        instance: the instance id.
        track: the instance's track id when it moves, else None.
        frame: the instance's frame (:func:`~vadgs.train.vad.survey.instance_frame`).
        cfg: the reconstruction's settings.
        generator: the random numbers of the selection.
        survey: the instance's survey, or None.

    Returns:
        The :class:`~vadgs.select.ViewSelection` of the supporting views.
    """
    covis = survey.covis if survey is not None and survey.covis is not None else None
    if covis is None:
        covis = frame.covis.restrict(frame.voxels)
    sel = _select_among(index, ref, instance, covis, frame, cfg, generator, survey)
    if not (cfg.seen_supports and sel.reason.startswith(("no_voxels", "no_candidates", "narrow_baselines"))):
        return sel
    views = [ref, *torch.nonzero(frame.allowed).flatten().tolist()]
    covis = index.seen_covis(frame.voxels, views, track)
    shown = len(covis.voxels_of(ref))
    if not shown:
        return sel
    if shown < cfg.selection.min_shared:
        cfg = replace(cfg, selection=replace(cfg.selection, min_shared=shown))
    seen = _select_among(index, ref, instance, covis, frame, cfg, generator, survey)
    return replace(seen, reason=f"{seen.reason} (seen)")


def _select_among(
    index: VisibilityIndex,
    ref: int,
    instance: int,
    covis: Covisibility,
    frame: InstanceFrame,
    cfg: ReconstructConfig,
    generator: torch.Generator | None,
    survey: InstanceSurvey | None = None,
) -> ViewSelection:
    """:func:`select_views` on ``covis``, among the views showing the whole instance when it can."""
    focal = float(index.cameras.K[ref, 0, 0]) if cfg.selection.min_parallax else None  # one read
    if cfg.whole_supports:
        known = survey is not None and bool(survey.allowed)
        views = [v for v, a in enumerate(survey.allowed) if a] if survey is not None else []
        if survey is not None and known and all(v in survey.cut for v in [ref, *views]):
            allowed = list(survey.allowed)
            cuts = [survey.cut[v] for v in [ref, *views]]
        else:
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
    stats: tuple[float, float, float], cfg: ReconstructConfig, lengths: dict
) -> tuple[float, float]:
    """PatchMatch's depth range from a pair's ``(n, near, far)`` (:attr:`InstanceSurvey.depths`).

    The fallback range without a voxel in front.
    """
    n, z_min, z_max = stats
    near, far = cfg.depth_margin
    lo, hi = (z_min * near, z_max * far) if n else lengths["fallback_depth_range"]
    lo = max(lo, lengths["min_depth"])
    return (lo, max(hi, lo * 4, lengths["min_depth_span"]))


@torch.no_grad()
def plan_matches(
    index: VisibilityIndex,
    refs: Sequence[int],
    instance: int,
    config: ReconstructConfig | None = None,
    generator: torch.Generator | None = None,
    render_prior: Callable[[int], ViewRender] | None = None,
    device: torch.device | str | None = None,
    survey: InstanceSurvey | None = None,
) -> list[MatchPlan | InstanceReconstruction]:
    """Steps 1–3a of :func:`reconstruct_instance` for each of an instance's references ``refs``.

    Frame, view selection, crops and depth range of each (instance, reference) pair, in the order
    of ``refs`` (the selections draw from ``generator`` in that order). Per pair its
    :class:`~vadgs.train.vad.matching.MatchPlan`, or its (empty) :class:`InstanceReconstruction`
    with the reason when there is nothing to match. Cheap next to the matching: an event plans
    every pair first and matches them together (:func:`~vadgs.train.vad.matching.match_plans`).

    The host reads, for an instance whose own voxels stand for it: the ``survey``
    (:func:`~vadgs.train.vad.survey.survey_instance` of at least ``refs``; made here when not
    given), each pair's view selection and crops, and the plans' work, together.
    """
    cfg = _scaled_config(index, config)
    refs = [int(r) for r in refs]
    inputs = index.inputs
    for ref in refs:
        if not 0 <= ref < inputs.num_views:
            raise ValueError(f"ref: expected a view in [0, {inputs.num_views}), got {ref}")
    if survey is None or survey.instance != instance or not set(refs) <= set(survey.pixels):
        survey = survey_instance(index, instance, refs, cfg)
    if device is None and render_prior is not None and refs:
        device = render_maps(render_prior, refs[0])[0].device
    dev = torch.device(device) if device is not None else index.cameras.K.device
    out: list[MatchPlan | InstanceReconstruction] = []
    pixels: list[torch.Tensor] = []  # each plan's reference pixels, read together
    with checking(False):  # see reconstruct_instance
        for ref in refs:
            got = _plan_one(index, ref, survey, cfg, generator, dev)
            if isinstance(got, InstanceReconstruction):
                out.append(got)
                continue
            plan, px = got
            out.append(plan)
            pixels.append(px.to(dev))
        counts = torch.stack(pixels).double().tolist() if pixels else []  # one read
    counted = iter(counts)
    return [
        p if isinstance(p, InstanceReconstruction)
        else p._replace(work=match_work(next(counted), len(p.group) - 1, cfg.patchmatch))
        for p in out
    ]  # fmt: skip


def _plan_one(
    index: VisibilityIndex,
    ref: int,
    survey: InstanceSurvey,
    cfg: ReconstructConfig,
    generator: torch.Generator | None,
    dev: torch.device,
) -> tuple[MatchPlan, torch.Tensor] | InstanceReconstruction:
    """One pair's plan (its work left at 0) and its reference pixels on the device, or why not."""
    instance, track = survey.instance, survey.track

    def nothing(reason: str, views: list[int] | None = None) -> InstanceReconstruction:
        return _nothing(reason, ref, track, dev, views)

    if survey.pixels[ref] < cfg.min_pixels:
        return nothing("instance_too_small_in_reference")
    got = reference_frame(index, ref, survey, cfg)  # 1. voxels and frame
    if isinstance(got, str):
        return nothing(got)
    frame, stats = got
    sel = select_supports(index, ref, instance, track, frame, cfg, generator, survey)  # 2.
    group = [ref, *sel.ids]
    if len(group) < 2:
        return nothing(f"selection:{sel.reason}")
    crops = crop_group(index, group, instance, track, cfg, dev)  # 3a. crops
    if isinstance(crops, str):
        return nothing(crops, group)
    w2c = frame.world_to_cam[group]
    ch, cw = crops.size
    pixels = torch.stack([crops.masks[i][y0 : y0 + ch, x0 : x0 + cw].sum() for i, (y0, x0) in
                          zip(crops.members, crops.corners)]).sum()  # fmt: skip
    lengths = scene_lengths(
        index.scene_depth, fallback_depth_range=cfg.fallback_depth_range, min_depth=cfg.min_depth
    )
    depth_range = _depth_range(stats, cfg, lengths)
    return MatchPlan(ref, instance, track, group, crops, w2c.to(dev), depth_range, sel.reason, 0.0), pixels


def _scaled_config(index: VisibilityIndex, config: ReconstructConfig | None) -> ReconstructConfig:
    """``config`` (or the defaults) with the selection's ``eps`` scaled to the scene's depth."""
    cfg = config or reconstruct_config.ReconstructConfig()
    unit = index.scene_depth / REFERENCE_DEPTH  # the lengths follow the scene (scene_lengths)
    return replace(cfg, selection=replace(cfg.selection, eps=cfg.selection.eps * unit))


def _nothing(
    reason: str, ref: int, track: int | None, dev: torch.device, views: list[int] | None = None
) -> InstanceReconstruction:
    empty3 = torch.zeros(0, 3, device=dev)
    return InstanceReconstruction(
        empty3, empty3, empty3, torch.zeros(0, device=dev), track, views or [ref], [], [], reason
    )


@torch.no_grad()
def finish_match(
    index: VisibilityIndex,
    plan: MatchPlan,
    matched: MatchedCrops,
    config: ReconstructConfig | None = None,
    generator: torch.Generator | None = None,
    render_prior: Callable[[int], ViewRender] | None = None,
    occupied: torch.Tensor | None = None,
) -> InstanceReconstruction:
    """Steps 4–6 of :func:`reconstruct_instance` on a plan's matched crops (``match_plans``)."""
    cfg = _scaled_config(index, config)
    crops, group, w2c, track = plan.crops, plan.group, plan.world_to_cam, plan.track
    dev = matched.images.device
    with checking(False):  # see reconstruct_instance
        planar = cfg.planar is not None and track is None  # a car is not planar
        cons = consistent_depth(matched, crops, group, w2c, planar, cfg, generator)  # 4.
        # 5. the pixels the members' own LiDAR does not contradict, then the unexplained ones
        disagrees = None  # a 0-d bool on the device: read only when nothing else is left
        # on a scene with LiDAR (an SfM track's sparse voxels measure no pixel)
        if cfg.max_lidar_error is not None and index.inputs.lidar is not None:
            lidar = lidar_check(index, cons, crops, group, cfg, track)
            checked, bad = lidar.checked.sum(), lidar.contradicted.sum()
            disagrees = (checked >= max(cfg.min_pixels, 1)) & (bad > cfg.max_lidar_disagreement * checked)
            keep = cons.keep & ~lidar.contradicted & ~disagrees
            cons = cons._replace(keep=keep)
        new = cons.keep & ~explained_pixels(index, cons, crops, group, cfg, render_prior)
        points, normals, colors, spacing, consistent = fuse_points(
            index, cons, matched, crops, new, track, cfg, occupied, generator, dev
        )  # one point per such pixel, in the instance's frame, thinned
        full_depth, full_normal = depth_priors(cons, crops, index.cameras.image_size)  # 6.
        views = [group[i] for i in crops.members]
        reason = "ok" if points.shape[0] else ("explained" if consistent else "no_consistent_pixels")
        if not points.shape[0] and disagrees is not None and bool(disagrees):
            reason = "lidar_disagrees"
        reason += " (seen)" if plan.selection.endswith("(seen)") else ""  # selected on the z-buffers
        return InstanceReconstruction(
            points, normals, colors, spacing, track, views, full_depth, full_normal, reason, plan.work,
            consistent,
        )  # fmt: skip


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
    per cell of the point spacing by :func:`~vadgs.geometry.points.thin_points`), depth priors.

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
    (plan,) = plan_matches(index, [ref], instance, config, generator, render_prior, device)
    if isinstance(plan, InstanceReconstruction):
        return plan
    (matched,) = match_plans(index, [plan], _scaled_config(index, config), render_prior)
    return finish_match(index, plan, matched, config, generator, render_prior, occupied)
