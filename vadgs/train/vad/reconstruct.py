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

This module holds steps 1–3 (:func:`instance_frame`, ``select_supports``, :func:`match_plans`, and
:func:`match_work`, the matching's cost) and :func:`reconstruct_instance`, which runs them all on
the device of the index, in three parts that an event runs over all its (instance, reference)
pairs: :func:`plan_match` (steps 1–3a, pair by pair: a :class:`MatchPlan`), :func:`match_plans`
(step 3b, every pair's PatchMatch in few batched calls) and :func:`finish_match` (steps 4–6, pair
by pair); step 3's crops and matching scale live in :mod:`vadgs.train.vad.crops`
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
from vadgs.mvs.patchmatch import PatchMatchConfig, PatchMatchResult, patchmatch
from vadgs.select.covisibility import Covisibility
from vadgs.select.selector import ViewSelection, select_views
from vadgs.train.vad import reconstruct_config
from vadgs.train.vad.crops import Crops, MatchedCrops, crop_group, render_maps, to_scale
from vadgs.train.vad.fusion import consistent_depth, depth_priors, explained_pixels, fuse_points
from vadgs.train.vad.lengths import REFERENCE_DEPTH, scene_lengths

if TYPE_CHECKING:
    from vadgs.train.vad.reconstruct_config import ReconstructConfig
    from vadgs.train.vad.visibility import VisibilityIndex

__all__ = [
    "MAX_CALL_PIXEL_VIEWS",
    "InstanceFrame",
    "InstanceReconstruction",
    "MatchInputs",
    "MatchPlan",
    "ViewRender",
    "finish_match",
    "instance_frame",
    "match_batches",
    "match_plans",
    "match_work",
    "plan_match",
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
    return InstanceFrame(index.covis, voxels, index.cameras.world_to_cam, index.allowed)


def select_supports(
    index: VisibilityIndex,
    ref: int,
    instance: int,
    track: int | None,
    frame: InstanceFrame,
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

    Args:
        index: the scene's visibility index.
        ref: the reference view.
        instance: the instance id.
        track: the instance's track id when it moves, else None.
        frame: the instance's frame (:func:`instance_frame`).
        cfg: the reconstruction's settings.
        generator: the random numbers of the selection.

    Returns:
        The :class:`~vadgs.select.ViewSelection` of the supporting views.
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
    frame: InstanceFrame,
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
    frame: InstanceFrame, w2c_ref: torch.Tensor, cfg: ReconstructConfig, lengths: dict, pixels: torch.Tensor
) -> tuple[tuple[float, float], float]:
    """PatchMatch's depth range from the instance's voxels as the reference sees them, and ``pixels``.

    ``pixels`` (a count on the device, read in the same read) is the matching's reference pixels.
    """
    cen = frame.covis.voxel_centers
    z = cen @ w2c_ref[2, :3] + w2c_ref[2, 3]  # every voxel's (no data-dependent selection: no read)
    front = frame.voxels & (z > lengths["min_voxel_depth"])
    inf = torch.full_like(z, math.inf)
    n, z_min, z_max = 0, 0.0, 0.0
    if z.numel():
        n, z_min, z_max, count = torch.stack(
            [
                front.sum().double(),
                torch.where(front, z, inf).min().double(),
                torch.where(front, z, -inf).max().double(),
                pixels.double(),
            ]
        ).tolist()  # one read
    else:
        count = float(pixels)
    near, far = cfg.depth_margin
    lo, hi = (z_min * near, z_max * far) if n else lengths["fallback_depth_range"]
    lo = max(lo, lengths["min_depth"])
    return (lo, max(hi, lo * 4, lengths["min_depth_span"])), count


class MatchPlan(NamedTuple):
    """An (instance, reference) pair selected and cropped, ready for PatchMatch (:func:`plan_match`).

    Attributes:
        ref: the reference view.
        instance: the instance id.
        track: the track id when the instance moves, else None.
        group: the reference, then its supporting views.
        crops: the group's :class:`~vadgs.train.vad.crops.Crops`.
        world_to_cam: ``(G, 4, 4)`` the group's poses in the instance's frame, on the device.
        depth_range: PatchMatch's ``(near, far)`` for this pair.
        selection: the view selection's reason (``" (seen)"`` at its end: on the z-buffers).
        work: PatchMatch's work on the pair (:func:`match_work`).
    """

    ref: int
    instance: int
    track: int | None
    group: list[int]
    crops: Crops
    world_to_cam: torch.Tensor
    depth_range: tuple[float, float]
    selection: str
    work: float


class MatchInputs(NamedTuple):
    """One plan's PatchMatch inputs, one row per member (``b``), sources ``V`` of size ``(hs, ws)``."""

    images: torch.Tensor  # (b, 3, ch, cw)
    masks: torch.Tensor  # (b, 1, ch, cw) bool
    K: torch.Tensor  # (b, 3, 3)
    w2c: torch.Tensor  # (b, 4, 4)
    init_depth: torch.Tensor | None  # (b, 1, ch, cw)
    init_normal: torch.Tensor | None  # (b, 3, ch, cw)
    src_images: torch.Tensor  # (b, V, 3, hs, ws)
    src_K: torch.Tensor  # (b, V, 3, 3)
    src_w2c: torch.Tensor  # (b, V, 4, 4)
    src_masks: torch.Tensor  # (b, V, 1, hs, ws) bool


def _match_inputs(
    index: VisibilityIndex, plan: MatchPlan, render_prior: Callable[[int], ViewRender] | None
) -> MatchInputs:
    """Step 3b's inputs of one plan: each member's crop as reference against all other group views."""
    crops, group, world_to_cam = plan.crops, plan.group, plan.world_to_cam
    ch, cw = crops.size
    dev = crops.images.device
    ref_imgs, ref_masks, corners, init_d, init_n = [], [], [], [], []
    for i, (y0, x0) in zip(crops.members, crops.corners):
        ref_imgs.append(crops.images[i, :, y0 : y0 + ch, x0 : x0 + cw])
        ref_masks.append(crops.masks[i][None, y0 : y0 + ch, x0 : x0 + cw])
        corners.append((x0, y0))
        if render_prior is not None:
            d, _, n = render_maps(render_prior, group[i], index)
            d, n = d.to(dev), n.to(dev)
            known = d > 0
            d, n = to_scale(d, known, crops.scale), to_scale(n, known, crops.scale, unit=True)
            init_d.append(d[:, y0 : y0 + ch, x0 : x0 + cw])
            init_n.append(n[:, y0 : y0 + ch, x0 : x0 + cw])
    members = torch.tensor(crops.members, device=dev)
    shift = torch.zeros(len(corners), 3, 3, device=dev, dtype=crops.K.dtype)
    shift[:, :2, 2] = torch.tensor(corners, device=dev, dtype=crops.K.dtype)
    others = torch.tensor([[j for j in range(len(group)) if j != i] for i in crops.members], device=dev)
    return MatchInputs(
        torch.stack(ref_imgs),
        torch.stack(ref_masks),
        crops.K[members] - shift,  # shift_K of each member's crop
        world_to_cam[members],
        torch.stack(init_d) if init_d else None,
        torch.stack(init_n) if init_n else None,
        crops.images[others],
        crops.K[others],
        world_to_cam[others],
        crops.regions[others],
    )


#: At most this many padded reference pixel-views (members x crop pixels x source views) in one
#: PatchMatch call of :func:`match_plans`: on a GPU a call scores everything at once, and its
#: temporaries grow with it (about one large pair's today: up to ~2 GB).
MAX_CALL_PIXEL_VIEWS = 1 << 20


def match_batches(
    inputs: list[MatchInputs], padding: float | None, top_k: int, mean: bool
) -> list[list[int]]:
    """The plans matched together, in groups of one PatchMatch call each.

    A call's padded crop (the largest height by the largest width) is at most ``padding`` times
    any of its crops, and it holds at most :data:`MAX_CALL_PIXEL_VIEWS` pixel-views. Plans of
    fewer source views than the others are padded with views that match nothing, which
    changes nothing but the ``top_k`` fallback of fewer than ``top_k`` views and ``"mean"``
    aggregation (``mean``): such plans are matched only with plans of as many views.

    Only the inputs' shapes are read (``images`` and ``src_images``).

    Returns:
        The indices of ``inputs`` of each call, in ascending order within a call.
    """
    order = sorted(range(len(inputs)), key=lambda i: -inputs[i].images.shape[-2] * inputs[i].images.shape[-1])
    out: list[dict] = []  # key (exact view count or -1), size, smallest area, references, views, plans
    for i in order:
        b, _, h, w = inputs[i].images.shape
        v = inputs[i].src_images.shape[1]
        key = v if (mean or v < top_k) else -1
        for batch in out:
            hh, ww = max(batch["h"], h), max(batch["w"], w)
            small = min(batch["small"], h * w)
            views = max(batch["views"], v)
            if (
                batch["key"] == key
                and (padding is None or hh * ww <= padding * small)
                and (batch["refs"] + b) * hh * ww * views <= MAX_CALL_PIXEL_VIEWS
            ):
                batch.update(h=hh, w=ww, small=small, views=views, refs=batch["refs"] + b)
                batch["plans"].append(i)
                break
        else:
            out.append({"key": key, "h": h, "w": w, "small": h * w, "refs": b, "views": v, "plans": [i]})
    return [sorted(batch["plans"]) for batch in out]


def _match_batch(
    parts: list[MatchInputs], ranges: list[tuple[float, float]], pm: PatchMatchConfig
) -> PatchMatchResult:
    """One :func:`~vadgs.mvs.patchmatch` call on the plans' inputs ``parts``, padded to one size."""
    if len(parts) == 1:
        p = parts[0]
        return patchmatch(
            p.images, p.src_images, p.K, p.src_K, p.w2c, p.src_w2c, ranges[0], pm,
            init_depth=p.init_depth, init_normal=p.init_normal, mask=p.masks, src_masks=p.src_masks,
        )  # fmt: skip
    size = (max(p.images.shape[-2] for p in parts), max(p.images.shape[-1] for p in parts))
    src_size = (max(p.src_images.shape[-2] for p in parts), max(p.src_images.shape[-1] for p in parts))
    views = max(p.src_images.shape[1] for p in parts)
    init = parts[0].init_depth is not None  # all or none: one render prior

    def cat(ts: list, fix: Callable[[torch.Tensor], torch.Tensor]) -> torch.Tensor:
        return torch.cat([fix(t) for t in ts])

    return patchmatch(
        cat([p.images for p in parts], lambda t: _pad_to(t, size)),
        cat([p.src_images for p in parts], lambda t: _pad_views(_pad_to(t, src_size), views)),
        torch.cat([p.K for p in parts]),
        cat([p.src_K for p in parts], lambda t: _pad_views(t, views)),
        torch.cat([p.w2c for p in parts]),
        cat([p.src_w2c for p in parts], lambda t: _pad_views(t, views)),
        [r for r, p in zip(ranges, parts) for _ in range(p.images.shape[0])],  # each reference's
        pm,
        init_depth=cat([p.init_depth for p in parts], lambda t: _pad_to(t, size)) if init else None,
        init_normal=cat([p.init_normal for p in parts], lambda t: _pad_to(t, size)) if init else None,
        mask=cat([p.masks for p in parts], lambda t: _pad_to(t, size, False)),
        # the padded views match nothing (an empty region: the worst cost there)
        src_masks=cat(
            [p.src_masks for p in parts], lambda t: _pad_views(_pad_to(t, src_size, False), views, True)
        ),
    )


def _pad_to(x: torch.Tensor, size: tuple[int, int], value: float | bool = 0) -> torch.Tensor:
    """``x`` ``(..., h, w)`` padded at the bottom and right to ``size`` (the intrinsics stay valid)."""
    h, w = x.shape[-2:]
    if (h, w) == size:
        return x
    lead = x.shape[:-2]
    flat = x.reshape(-1, 1, h, w)
    if flat.dtype == torch.bool:
        out = torch.nn.functional.pad(flat.to(torch.uint8), (0, size[1] - w, 0, size[0] - h)).bool()
    else:
        out = torch.nn.functional.pad(flat, (0, size[1] - w, 0, size[0] - h), value=float(value))
    return out.reshape(*lead, *size)


def _pad_views(x: torch.Tensor, views: int, empty: bool = False) -> torch.Tensor:
    """``x`` ``(b, V, ...)`` with its first view repeated (``empty``: zeros) up to ``views`` views."""
    extra = views - x.shape[1]
    if extra == 0:
        return x
    more = x[:, :1].expand(-1, extra, *x.shape[2:])
    return torch.cat([x, torch.zeros_like(more) if empty else more], 1)


@torch.no_grad()
def match_plans(
    index: VisibilityIndex,
    plans: list[MatchPlan],
    config: ReconstructConfig | None = None,
    render_prior: Callable[[int], ViewRender] | None = None,
) -> list[MatchedCrops]:
    """Step 3b for many plans: PatchMatch of every member crop of every plan, in few calls.

    Every member of every plan is one reference of a batched :func:`~vadgs.mvs.patchmatch` call
    against the other views of its group. Plans whose crops differ in size are padded (bottom and
    right: the crops' intrinsics stay valid; padded pixels outside the masks) to the largest of
    their call, at most ``config.match_padding`` times a crop's pixels, and at most
    :data:`MAX_CALL_PIXEL_VIEWS` padded pixel-views a call; sources to the largest
    source image, and to the most source views with views that match nothing (an empty region);
    each reference keeps its own depth range. One call per such batch (one for an event's pairs
    whose crops are of similar sizes); each plan's results are cut back to its own size.

    A batched call draws other random numbers than one call per plan, and its references score
    the union of their masks (padded pixels score nothing), so results agree with per-plan calls
    in distribution, not bit for bit (``tests/train/vad/test_vad_end_to_end.py``).

    Returns:
        Per plan, its :class:`~vadgs.train.vad.crops.MatchedCrops`.
    """
    cfg = config or reconstruct_config.ReconstructConfig()
    with checking(False):  # the plans' tensors are the index's (see reconstruct_instance)
        return _match_plans(index, plans, cfg, render_prior)


def _match_plans(
    index: VisibilityIndex,
    plans: list[MatchPlan],
    cfg: ReconstructConfig,
    render_prior: Callable[[int], ViewRender] | None,
) -> list[MatchedCrops]:
    inputs = [_match_inputs(index, plan, render_prior) for plan in plans]
    out: list[MatchedCrops | None] = [None] * len(plans)
    pm = cfg.patchmatch
    for batch in match_batches(inputs, cfg.match_padding, pm.top_k, pm.view_selection == "mean"):
        parts = [inputs[i] for i in batch]
        res = _match_batch(parts, [plans[i].depth_range for i in batch], pm)
        n0 = 0
        for i, p in zip(batch, parts):
            b, v = p.images.shape[0], p.src_images.shape[1]
            ch, cw = p.images.shape[-2:]
            cut = PatchMatchResult(
                *(
                    t[n0 : n0 + b, : (v if name == "view_costs" else None), :ch, :cw]
                    for name, t in zip(PatchMatchResult._fields, res)
                )
            )
            out[i] = MatchedCrops(cut, p.images, p.masks, p.K, p.w2c)
            n0 += b
    assert all(m is not None for m in out)
    return out  # type: ignore[return-value]


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
    return _work(float(masks.sum()), sources, config)


def _work(pixels: float, sources: int, config: PatchMatchConfig) -> float:
    """:func:`match_work` of ``pixels`` reference pixels (a number)."""
    levels = max(int(config.pyramid_levels), 1)
    sweeps = config.iterations * 4.0 ** -(levels - 1)
    sweeps += config.fine_iterations * sum(4.0**-k for k in range(levels - 1))
    return pixels * sources * sweeps


@torch.no_grad()
def plan_match(
    index: VisibilityIndex,
    ref: int,
    instance: int,
    config: ReconstructConfig | None = None,
    generator: torch.Generator | None = None,
    render_prior: Callable[[int], ViewRender] | None = None,
    device: torch.device | str | None = None,
) -> MatchPlan | InstanceReconstruction:
    """Steps 1–3a of :func:`reconstruct_instance`: frame, view selection, crops and depth range.

    Returns the pair's :class:`MatchPlan`, or its (empty) :class:`InstanceReconstruction` with the
    reason when there is nothing to match. Cheap next to the matching: an event plans every pair
    first and matches them together (:func:`match_plans`).
    """
    cfg = _scaled_config(index, config)
    lengths = scene_lengths(
        index.scene_depth, fallback_depth_range=cfg.fallback_depth_range, min_depth=cfg.min_depth
    )
    inputs = index.inputs
    if not 0 <= ref < inputs.num_views:
        raise ValueError(f"ref: expected a view in [0, {inputs.num_views}), got {ref}")
    track = instance if instance in inputs.tracks else None
    if device is None and render_prior is not None:
        device = render_maps(render_prior, ref)[0].device
    dev = torch.device(device) if device is not None else index.cameras.K.device

    def nothing(reason: str, views: list[int] | None = None) -> InstanceReconstruction:
        return _nothing(reason, ref, track, dev, views)

    with checking(False):  # see reconstruct_instance
        if int((index.instances(ref) == instance).sum()) < cfg.min_pixels:
            return nothing("instance_too_small_in_reference")
        frame = instance_frame(index, ref, instance, track, cfg)  # 1. voxels and frame
        if isinstance(frame, str):
            return nothing(frame)
        sel = select_supports(index, ref, instance, track, frame, cfg, generator)  # 2.
        group = [ref, *sel.views.tolist()]
        if len(group) < 2:
            return nothing(f"selection:{sel.reason}")
        crops = crop_group(index, group, instance, track, cfg, dev)  # 3a. crops
        if isinstance(crops, str):
            return nothing(crops, group)
        w2c = frame.world_to_cam[group]
        ch, cw = crops.size
        pixels = torch.stack([crops.masks[i][y0 : y0 + ch, x0 : x0 + cw].sum() for i, (y0, x0) in
                              zip(crops.members, crops.corners)]).sum()  # fmt: skip
        depth_range, count = _depth_range(frame, w2c[0].to(frame.covis.voxel_centers.device), cfg, lengths,
                                          pixels.to(frame.covis.voxel_centers.device))  # fmt: skip
        work = _work(count, len(group) - 1, cfg.patchmatch)
        return MatchPlan(ref, instance, track, group, crops, w2c.to(dev), depth_range, sel.reason, work)


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
    """Steps 4–6 of :func:`reconstruct_instance` on a plan's matched crops (:func:`match_plans`)."""
    cfg = _scaled_config(index, config)
    crops, group, w2c, track = plan.crops, plan.group, plan.world_to_cam, plan.track
    dev = matched.images.device
    with checking(False):  # see reconstruct_instance
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
    plan = plan_match(index, ref, instance, config, generator, render_prior, device)
    if isinstance(plan, InstanceReconstruction):
        return plan
    (matched,) = match_plans(index, [plan], _scaled_config(index, config), render_prior)
    return finish_match(index, plan, matched, config, generator, render_prior, occupied)
