r"""Reconstruct one flagged instance by multi-view stereo (paper, Fig. 2 and 4).

:func:`reconstruct_instance`, given the scene's :class:`~vadgs.train.visibility.VisibilityIndex`
(:mod:`vadgs.train.visibility`; re-exported here with :func:`build_visibility_index`), a
reference view and an instance flagged by :func:`~vadgs.train.incomplete.find_incomplete`:

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

Each step is a small function (``_instance_frame``, :func:`~vadgs.select.select_views`,
``_crop_group`` and ``_match``, ``_consistent``, fusion, ``_depth_priors``) on the device of the
index.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import NamedTuple

import torch
import torch.nn.functional as F

from vadgs.geometry.camera import invert_rigid, scale_intrinsics
from vadgs.mvs.consistency import geometric_consistency
from vadgs.mvs.fusion import FusionConfig, fuse_depth_maps
from vadgs.mvs.patchmatch import PatchMatchConfig, PatchMatchResult, patchmatch
from vadgs.mvs.planar import PlanarCompletionConfig, complete_planar
from vadgs.select.covisibility import Covisibility
from vadgs.select.selector import ViewSelection, ViewSelectionConfig, select_views
from vadgs.train.inputs import sfm_observations
from vadgs.train.visibility import ViewCache, VisibilityIndex, build_visibility_index, derive_instance_map

__all__ = [
    "InstanceReconstruction",
    "MatchScale",
    "ReconstructConfig",
    "ViewCache",
    "ViewRender",
    "VisibilityIndex",
    "build_visibility_index",
    "derive_instance_map",
    "match_scale",
    "reconstruct_instance",
    "sfm_observations",
    "thin_points",
]


@dataclass(frozen=True)
class ReconstructConfig:
    """Settings of :func:`reconstruct_instance`.

    Attributes:
        selection: view selection (``k = 4`` supporting views by default; ``method="consecutive"``
            is the paper's "w/o view selection" ablation).
        patchmatch: PatchMatch settings.
        margin: pixels added around each instance's bounding box for the crops.
        max_crop: crops are limited to this many pixels per side (larger instances are
            reconstructed in their central part only; keeps the cost bounded).
        max_reproj_error: forward–backward reprojection threshold (px) of the consistency check.
        max_rel_depth: relative depth threshold of the consistency check.
        min_consistent_views: other group members that must confirm a pixel.
        min_instance_voxels: below this many own voxels, the voxels seen through the instance
            in the reference view stand in for its candidates.
        min_pixels: members whose instance mask has fewer pixels are used as sources only.
        max_points: cap on the points returned (random subset, seeded).
        max_upsample: small instances, whose crop is at most ``max_crop / f`` pixels, are matched
            at ``f`` times the scene's resolution, ``f`` up to this integer and never finer than
            the image files (``1 / scene.scale``): a sign 40 px tall at half resolution gets four
            times the pixels and half the depth error (on street_a: its MVS points within 5 cm of
            the true surface 35 % → 60 %, its surface covered 51 % → 65 %), while the crop stays
            within ``max_crop`` so the cost stays bounded. ``1``: always the scene's resolution.
        planar: planar completion of the textureless parts of static instances
            (:func:`vadgs.mvs.complete_planar`); ``None`` turns it off. Never applied to moving
            objects: a car is not planar, and one plane fitted to it fills many of its pixels off
            its surface. On by default since small instances are matched at a finer resolution
            (``max_upsample``): on street_a it took the sign's completeness in training from 76 %
            to 84 % at +0.3 dB (docs/results.md). (At the training resolution alone it had tilted
            the sign's board.)
        max_match_pixels: pixel budget of one member's instance mask at the matching scale:
            an instance larger than this (a facade filling the view) is matched at 1/2, 1/4, ...
            of the scene's resolution (down to ``1 / max_downsample``), so that an event's cost
            follows the number of instances rather than their size, and its points come at the
            spacing of that scale. ``None``: always the scene's resolution (or finer).
        max_downsample: the coarsest matching scale, ``1 / max_downsample`` (1, 2, 4 or 8).
        depth_margin: ``(near, far)`` factors on the nearest and farthest instance voxel depth in
            the reference view: PatchMatch's random depths are drawn in ``[near z_min, far z_max]``.
        fallback_depth_range: the depth range when the reference sees none of the voxels.
        min_depth: lower bound of the depth range.
        explained_alpha: a consistent pixel is *explained* (gives no point) where the member's
            render has at least this opacity and a depth in front of, or within
            ``explained_tolerance`` (relative) of, the MVS depth; it still gives a depth prior.
        explained_tolerance: see ``explained_alpha``.
        thin_points: keep one point per cell of the point spacing (the members see the same
            surface: without it, each surface patch becomes one point per member), at the scene's
            resolution or at the coarser matching scale; the points' ``spacing`` (the new Gaussians'
            width) is that of the cell. Finer matching of small instances then gives more accurate
            points, not more of them.
        thin_factor: for an instance matched below the scene's resolution (a large one, such as a
            facade: ``max_match_pixels``), the cell of ``thin_points`` is this many times the
            point spacing and the new Gaussians are as much wider: fewer, larger Gaussians on
            large surfaces. Smaller instances (a sign) keep one point per pixel footprint. 1: no
            change. 1.5 by default: on street_a 1.24x the baseline's Gaussians instead of 1.32x,
            PSNR 29.51 dB, sign and facades as at 1 (docs/results.md).
        whole_supports: when the instance is whole in the reference view (its mask does not touch
            the image border), select the supporting views among those where it is whole too, if
            there are ``selection.k`` of them (else among all). A view that cuts the instance off
            cannot confirm the part it does not show: on street_a the sign's top 0.3 m is above
            the frame of the close views the voxels favour, and stayed empty (82.8 % complete).
    """

    selection: ViewSelectionConfig = field(default_factory=lambda: ViewSelectionConfig(min_shared=2))
    patchmatch: PatchMatchConfig = field(default_factory=lambda: PatchMatchConfig(iterations=3))
    margin: int = 6
    max_crop: int = 160
    max_reproj_error: float = 2.0
    max_rel_depth: float = 0.01
    min_consistent_views: int = 1
    min_instance_voxels: int = 8
    min_pixels: int = 16
    max_points: int = 20000
    max_upsample: int = 2
    planar: PlanarCompletionConfig | None = field(default_factory=PlanarCompletionConfig)
    max_match_pixels: int | None = 2048
    max_downsample: int = 4
    depth_margin: tuple[float, float] = (0.5, 2.0)
    fallback_depth_range: tuple[float, float] = (0.5, 150.0)
    min_depth: float = 0.2
    explained_alpha: float = 0.7
    explained_tolerance: float = 0.05
    thin_points: bool = True
    thin_factor: float = 1.5
    whole_supports: bool = True

    def __post_init__(self) -> None:
        if not (isinstance(self.max_upsample, int) and self.max_upsample >= 1):
            raise ValueError(f"max_upsample: expected an integer >= 1, got {self.max_upsample!r}")
        if self.max_crop < 8:
            raise ValueError(f"max_crop: expected >= 8 pixels, got {self.max_crop}")
        if self.max_match_pixels is not None and self.max_match_pixels < 64:
            raise ValueError(f"max_match_pixels: expected None or >= 64, got {self.max_match_pixels}")
        if not self.thin_factor >= 1:
            raise ValueError(f"thin_factor: expected >= 1, got {self.thin_factor}")
        if self.max_downsample not in (1, 2, 4, 8):
            raise ValueError(f"max_downsample: expected 1, 2, 4 or 8, got {self.max_downsample}")
        near, far = self.depth_margin
        lo, hi = self.fallback_depth_range
        if not (0 < near <= 1 <= far and 0 < lo < hi and self.min_depth > 0):
            raise ValueError(
                "depth_margin, fallback_depth_range, min_depth: expected 0 < near <= 1 <= far, "
                f"0 < lo < hi and min_depth > 0, got {self.depth_margin}, {self.fallback_depth_range}, "
                f"{self.min_depth}"
            )


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
        reason: ``"ok"`` or why nothing (or little) was reconstructed.
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


class MatchScale(NamedTuple):
    """The scale an instance is matched at: ``up / down`` times the scene's resolution.

    At most one of the two is above 1: ``up`` for small instances (finer than the training
    images, up to the files' resolution), ``down`` for large ones (a power of two).
    """

    up: int = 1
    down: int = 1

    @property
    def value(self) -> float:
        """The scale as a number."""
        return self.up / self.down


def match_scale(
    mask_pixels: int, crop: tuple[int, int], native: int, config: ReconstructConfig | None = None
) -> MatchScale:
    """The matching scale of an instance of ``mask_pixels`` (largest member) in a crop ``(ch, cw)``.

    Small crops (at most ``max_crop / f`` per side) are matched ``f`` times finer, ``f`` up to
    ``max_upsample`` and ``native`` (the files' resolution over the scene's); otherwise, while the
    mask has more than ``max_match_pixels`` pixels at the scale, the scale halves (down to
    ``1 / max_downsample``).

    Example:
        >>> match_scale(300, (40, 30), native=2)  # a sign: twice finer
        MatchScale(up=2, down=1)
        >>> match_scale(6000, (144, 160), native=2)  # a facade: matched at half resolution
        MatchScale(up=1, down=2)
        >>> match_scale(6000, (144, 160), 2, ReconstructConfig(max_match_pixels=None))
        MatchScale(up=1, down=1)
    """
    cfg = config or ReconstructConfig()
    ch, cw = crop
    up = max(1, min(cfg.max_upsample, native, cfg.max_crop // max(ch, cw, 1)))
    if up > 1 or cfg.max_match_pixels is None:
        return MatchScale(up, 1)
    down = 1
    while down < cfg.max_downsample and mask_pixels / (down * down) > cfg.max_match_pixels:
        down *= 2
    return MatchScale(1, down)


def _crops(
    masks: Sequence[torch.Tensor], margin: int, size: tuple[int, int], max_crop: int
) -> tuple[list[tuple[int, int]], int, int]:
    """One crop size for all masks and each crop's top-left corner.

    The size is the largest bounding box plus margin (capped); each crop is centred on its mask's
    box and clipped to the image.
    """
    hh, ww = size
    centres, hs, ws = [], [], []
    for m in masks:
        ys, xs = m.nonzero(as_tuple=True)
        centres.append(((int(ys.min()) + int(ys.max())) // 2, (int(xs.min()) + int(xs.max())) // 2))
        hs.append(int(ys.max()) - int(ys.min()) + 1 + 2 * margin)
        ws.append(int(xs.max()) - int(xs.min()) + 1 + 2 * margin)
    ch, cw = min(max(hs), max_crop, hh), min(max(ws), max_crop, ww)
    corners = [(min(max(cy - ch // 2, 0), hh - ch), min(max(cx - cw // 2, 0), ww - cw)) for cy, cx in centres]
    return corners, ch, cw


def _align_crops(
    corners: list[tuple[int, int]], ch: int, cw: int, down: int, size: tuple[int, int]
) -> tuple[list[tuple[int, int]], int, int]:
    """Crops on the ``down x down`` block grid of the image (whole blocks only), covering the old ones."""
    hh, ww = (size[0] // down) * down, (size[1] // down) * down
    ch2, cw2 = min(-(-ch // down) * down, hh), min(-(-cw // down) * down, ww)
    out = [(min((y0 // down) * down, hh - ch2), min((x0 // down) * down, ww - cw2)) for y0, x0 in corners]
    return out, ch2, cw2


def _repeat(x: torch.Tensor, f: int) -> torch.Tensor:
    """Nearest upsampling of the last two dims by ``f`` (pixel (y, x) -> block (fy.., fx..))."""
    return x if f == 1 else x.repeat_interleave(f, -2).repeat_interleave(f, -1)


def _pool_valid(x: torch.Tensor, valid: torch.Tensor, f: int, unit: bool = False) -> torch.Tensor:
    """``(C, H, W)`` → ``(C, H/f, W/f)``: the mean of the valid pixels of each ``f x f`` block.

    Zero where fewer than half are valid (``unit``: renormalised, for normals); at ``f = 1``, ``x``
    with zeros outside ``valid``.
    """
    if f == 1:
        return torch.where(valid, x, torch.zeros_like(x))
    v = valid.to(x.dtype)
    cnt = F.avg_pool2d(v[None], f)[0]
    out = F.avg_pool2d((x * v)[None], f)[0] / cnt.clamp(min=1e-6)
    if unit:
        out = F.normalize(out, dim=0)
    return torch.where(cnt >= 0.5, out, torch.zeros_like(out))


def _pool_mask(m: torch.Tensor, f: int) -> torch.Tensor:
    """Bool ``(..., H, W)`` → ``(..., H/f, W/f)``: blocks where at least half the pixels are set."""
    if f == 1:
        return m
    lead = m.shape[:-2]
    x = F.avg_pool2d(m.reshape(-1, 1, *m.shape[-2:]).float(), f)
    return (x >= 0.5).reshape(*lead, *x.shape[-2:])


def _to_scale(x: torch.Tensor, valid: torch.Tensor, scale: MatchScale, unit: bool = False) -> torch.Tensor:
    """A scene-resolution map ``(C, H, W)`` at the matching scale (valid-pixel means when coarser)."""
    if scale.up > 1:
        return _repeat(torch.where(valid, x, torch.zeros_like(x)), scale.up)
    return _pool_valid(x, valid, scale.down, unit)


def _shift_K(K: torch.Tensor, x0: int, y0: int) -> torch.Tensor:
    K = K.clone()
    K[..., 0, 2] -= x0
    K[..., 1, 2] -= y0
    return K


class _InstanceFrame(NamedTuple):
    """Step 1's result: where the instance is matched and which voxels stand for it."""

    covis: Covisibility
    voxels: torch.Tensor  # (M,) bool
    world_to_cam: torch.Tensor  # (V, 4, 4): world (static) or object frame (track) to each view
    allowed: torch.Tensor  # (V,) bool: views that may support


class _Crops(NamedTuple):
    """Step 3's input: the group's images and masks cropped around the instance, at the matching scale."""

    members: list[int]  # group positions whose instance mask is large enough to be a reference
    images: torch.Tensor  # (G, 3, h, w) full images of the group at the matching scale
    masks: list[torch.Tensor]  # per group view (h, w): the instance
    regions: torch.Tensor  # (G, 1, h, w): where sources may match (static or the object)
    K: torch.Tensor  # (G, 3, 3) at the matching scale
    corners: list[tuple[int, int]]  # per member: top-left of its crop, at the matching scale
    size: tuple[int, int]  # crop (ch, cw) at the matching scale
    corners_lo: list[tuple[int, int]]  # the same at the scene's resolution
    size_lo: tuple[int, int]
    scale: MatchScale


class _Matched(NamedTuple):
    """Step 3b's result: PatchMatch of each member's crop, with that crop's inputs."""

    result: PatchMatchResult
    images: torch.Tensor  # (b, 3, ch, cw) the members' crops
    masks: torch.Tensor  # (b, 1, ch, cw)
    K: torch.Tensor  # (b, 3, 3) of the crops
    world_to_cam: torch.Tensor  # (b, 4, 4)


class _Consistent(NamedTuple):
    """Step 4's result, per member crop."""

    depth: torch.Tensor  # (b, 1, ch, cw)
    normal: torch.Tensor  # (b, 3, ch, cw) camera frame
    keep: torch.Tensor  # (b, 1, ch, cw) bool: consistent (or planar-completed)


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
    if int(voxels.sum()) < cfg.min_instance_voxels:
        _, vidx = index.voxel_raster(ref)
        through = torch.unique(vidx[(index.instances(ref) == instance) & (vidx >= 0)])
        voxels = voxels.clone()
        voxels[through] = True
    if int(voxels.sum()) == 0:
        return "no_voxels"
    return _InstanceFrame(index.covis, voxels, index.cameras.world_to_cam, index.allowed)


def _select_supports(
    index: VisibilityIndex,
    ref: int,
    instance: int,
    frame: _InstanceFrame,
    cfg: ReconstructConfig,
    generator: torch.Generator | None,
) -> ViewSelection:
    """Step 2: the supporting views (``cfg.whole_supports``: among the views showing all of the instance)."""
    covis = frame.covis.restrict(frame.voxels)
    if cfg.whole_supports and not index.cut_by_border(ref, instance):
        views = torch.nonzero(frame.allowed).flatten().tolist()
        cut = torch.tensor([index.cut_by_border(v, instance) for v in views], dtype=torch.bool)
        whole = frame.allowed.clone()
        whole[torch.tensor(views, dtype=torch.long, device=whole.device)[cut.to(whole.device)]] = False
        if int(whole.sum()) > cfg.selection.k:  # the reference is one of them
            sel = select_views(ref, covis, cfg.selection, generator, whole)
            if len(sel.views) == cfg.selection.k:
                return sel
    return select_views(ref, covis, cfg.selection, generator, frame.allowed)


def _depth_range(frame: _InstanceFrame, w2c_ref: torch.Tensor, cfg: ReconstructConfig) -> tuple[float, float]:
    """PatchMatch's depth range from the instance's voxels as the reference sees them."""
    cen = frame.covis.voxel_centers[frame.voxels]
    z = cen @ w2c_ref[2, :3] + w2c_ref[2, 3]
    z = z[z > 0.1]
    near, far = cfg.depth_margin
    lo, hi = (float(z.min()) * near, float(z.max()) * far) if z.numel() else cfg.fallback_depth_range
    lo = max(lo, cfg.min_depth)
    return lo, max(hi, lo * 4, 1.0)


def _crop_group(
    index: VisibilityIndex,
    group: list[int],
    instance: int,
    track: int | None,
    cfg: ReconstructConfig,
    device: torch.device,
) -> _Crops | str:
    """Step 3a: crops around the instance in each group view, at its matching scale (:func:`match_scale`).

    Sources match only inside their region: static pixels for a static instance, the object's own
    pixels for a moving one. The group's images, masks and intrinsics move to ``device`` (where
    the matching runs), once.
    """
    inputs = index.inputs
    h, w = index.cameras.image_size
    masks = [index.instances(v) == instance for v in group]
    sizes = [int(m.sum()) for m in masks]
    members = [i for i, n in enumerate(sizes) if n >= cfg.min_pixels]
    if len(members) < 2:
        return "instance_seen_in_fewer_than_two_group_views"
    corners, ch, cw = _crops([masks[i] for i in members], cfg.margin, (h, w), cfg.max_crop)
    native = inputs.native_factor  # the files' resolution
    scale = match_scale(max(sizes[i] for i in members), (ch, cw), native, cfg)
    if scale.down > 1:
        corners, ch, cw = _align_crops(corners, ch, cw, scale.down, (h, w))

    def region(v: int) -> torch.Tensor:
        ins = index.instances(v)
        if track is not None:
            return ins == instance
        static = ~torch.isin(ins, torch.tensor(sorted(inputs.tracks), dtype=ins.dtype, device=ins.device))
        return static & index.valid(v)

    regions = torch.stack([region(v) for v in group])[:, None]
    K = index.cameras.K[group]
    corners_lo, size_lo = corners, (ch, cw)
    if scale.up > 1:
        f = scale.up
        masks = [_repeat(m, f) for m in masks]
        regions = _repeat(regions, f)
        corners, ch, cw = [(y0 * f, x0 * f) for y0, x0 in corners], ch * f, cw * f
        K = scale_intrinsics(K, f)
        images = torch.stack([index.image(v, f) for v in group])
    else:
        f = scale.down
        images = torch.stack([index.image(v) for v in group])
        if f > 1:
            masks = [_pool_mask(m, f) for m in masks]
            regions = _pool_mask(regions, f)
            corners, ch, cw = [(y0 // f, x0 // f) for y0, x0 in corners], ch // f, cw // f
            K = scale_intrinsics(K, 1.0 / f)
            images = F.avg_pool2d(images, f)
    images, regions, K = images.to(device), regions.to(device), K.to(device)
    masks = [m.to(device) for m in masks]
    return _Crops(members, images, masks, regions, K, corners, (ch, cw), corners_lo, size_lo, scale)


def _renders(
    render_prior, view: int, index: VisibilityIndex | None = None
) -> tuple[torch.Tensor, torch.Tensor | None, torch.Tensor]:
    """``(depth, alpha or None, normals)`` of a render prior's answer (a ViewRender or a pair).

    Padded to the index's size when ``index`` is given (views of different sizes).
    """
    out = render_prior(view)
    d, a, n = (out[0], None, out[1]) if isinstance(out, tuple) and len(out) == 2 else out
    if index is not None:
        d, n = index.pad(d), index.pad(n)
        a = None if a is None else index.pad(a)
    return d, a, n


def _match(
    index: VisibilityIndex,
    crops: _Crops,
    group: list[int],
    world_to_cam: torch.Tensor,
    depth_range: tuple[float, float],
    cfg: ReconstructConfig,
    render_prior: Callable[[int], ViewRender] | None,
) -> _Matched:
    """Step 3b: PatchMatch on the group, each member's crop as reference against all other views."""
    ch, cw = crops.size
    dev = crops.images.device
    ref_imgs, ref_masks, ref_K, init_d, init_n = [], [], [], [], []
    for i, (y0, x0) in zip(crops.members, crops.corners):
        ref_imgs.append(crops.images[i, :, y0 : y0 + ch, x0 : x0 + cw])
        ref_masks.append(crops.masks[i][None, y0 : y0 + ch, x0 : x0 + cw])
        ref_K.append(_shift_K(crops.K[i], x0, y0))
        if render_prior is not None:
            d, _, n = _renders(render_prior, group[i], index)
            d, n = d.to(dev), n.to(dev)
            known = d > 0
            d, n = _to_scale(d, known, crops.scale), _to_scale(n, known, crops.scale, unit=True)
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
    return _Matched(
        res, torch.stack(ref_imgs), torch.stack(ref_masks), torch.stack(ref_K), world_to_cam[crops.members]
    )


def _consistent(
    matched: _Matched,
    crops: _Crops,
    group: list[int],
    world_to_cam: torch.Tensor,
    planar: bool,
    cfg: ReconstructConfig,
    generator: torch.Generator | None,
) -> _Consistent:
    """Step 4: keep the pixels that other members confirm; planar completion of static instances."""
    res, w2c = matched.result, matched.world_to_cam
    depth = torch.where(res.mask, res.depth, torch.zeros_like(res.depth))
    b = len(crops.members)
    src = [[j for j in range(b) if j != i] for i in range(b)]
    cons = geometric_consistency(
        depth,
        matched.K,
        w2c,
        torch.stack([depth[o] for o in src]),
        torch.stack([matched.K[o] for o in src]),
        torch.stack([w2c[o] for o in src]),
        cfg.max_reproj_error,
        cfg.max_rel_depth,
        min(cfg.min_consistent_views, b - 1),
    )
    keep = cons.mask & res.mask
    normal = res.normal
    if planar:
        normal = res.normal.clone()
        c2w = invert_rigid(w2c)
        for k in range(b):
            o = [j for j in range(len(group)) if j != crops.members[k]]
            d_k, n_k, add = complete_planar(
                depth[k], keep[k], matched.masks[k], matched.images[k], matched.K[k], c2w[k],
                crops.images[o], torch.stack([crops.masks[j] for j in o])[:, None], crops.K[o],
                world_to_cam[o], cfg.planar, generator, res.normal[k],
            )  # fmt: skip
            depth[k] = d_k
            keep[k] |= add
            normal[k] = torch.where(add, n_k[:, None, None].expand_as(normal[k]), normal[k])
    return _Consistent(depth, normal, keep)


def _explained(
    index: VisibilityIndex,
    cons: _Consistent,
    crops: _Crops,
    group: list[int],
    cfg: ReconstructConfig,
    render_prior: Callable[[int], ViewRender] | None,
) -> torch.Tensor:
    """Step 5a: ``(b, 1, ch, cw)`` consistent pixels that an opaque rendered surface already explains.

    Each member's MVS depth is compared with that member's own render (at the matching scale):
    explained where the render has opacity ``>= explained_alpha`` and a depth in front of, or within
    ``explained_tolerance`` of, the MVS depth. Those pixels give priors but no new point.
    """
    out = torch.zeros_like(cons.keep)
    if render_prior is None:
        return out
    ch, cw = crops.size
    dev = cons.depth.device
    for k, (i, (y0, x0)) in enumerate(zip(crops.members, crops.corners)):
        d, a, _ = _renders(render_prior, group[i], index)
        if a is None:
            continue
        d, a = d.to(dev), a.to(dev)
        if crops.scale.up > 1:
            d, a = _repeat(d, crops.scale.up), _repeat(a, crops.scale.up)
        elif crops.scale.down > 1:
            d = _pool_valid(d, d > 0, crops.scale.down)
            a = F.avg_pool2d(a[None], crops.scale.down)[0]
        d, a = d[:, y0 : y0 + ch, x0 : x0 + cw], a[:, y0 : y0 + ch, x0 : x0 + cw]
        mvs = cons.depth[k]
        out[k] = (a >= cfg.explained_alpha) & (d > 0) & (d <= mvs * (1 + cfg.explained_tolerance))
    return out & cons.keep


def thin_points(points: torch.Tensor, cell: float, existing: torch.Tensor | None = None) -> torch.Tensor:
    """Keep one point per ``cell``-sized voxel, and none in a voxel that ``existing`` points occupy.

    Args:
        points: ``(P, 3)``, in their priority order (the first point of a voxel is kept).
        cell: voxel edge.
        existing: optional ``(Q, 3)`` points (same frame) whose voxels are taken.

    Returns:
        ``(P,)`` bool: the points kept. On the device of ``points``.

    Example:
        >>> p = torch.tensor([[0.01, 0.0, 0.0], [0.02, 0.0, 0.0], [0.31, 0.0, 0.0]])
        >>> thin_points(p, 0.1).tolist()
        [True, False, True]
        >>> thin_points(p, 0.1, existing=torch.tensor([[0.35, 0.05, 0.05]])).tolist()
        [True, False, False]
    """
    if points.shape[0] == 0:
        return torch.zeros(0, dtype=torch.bool, device=points.device)
    cell = max(float(cell), 1e-6)
    every = points if existing is None else torch.cat([existing.to(points), points])
    q = torch.floor(every / cell).long()
    q = q - q.min(0).values
    span = q.max(0).values + 1
    keys = (q[:, 0] * span[1] + q[:, 1]) * span[2] + q[:, 2]
    uniq, inv = torch.unique(keys, return_inverse=True)
    order = torch.arange(keys.shape[0], device=keys.device)
    first = torch.full((uniq.shape[0],), keys.shape[0], dtype=torch.long, device=keys.device)
    first = first.scatter_reduce(0, inv, order, reduce="amin")
    keep = first[inv] == order
    return keep[every.shape[0] - points.shape[0] :]


def _depth_priors(cons: _Consistent, crops: _Crops, size: tuple[int, int]) -> tuple[list, list]:
    """Step 6: each member's consistent depth and normals in its full image at the scene's resolution."""
    h, w = size
    ch, cw = crops.size_lo
    full_depth, full_normal = [], []
    for k, (y0, x0) in enumerate(crops.corners_lo):
        fd = cons.depth.new_zeros(1, h, w)
        fn = cons.normal.new_zeros(3, h, w)
        if crops.scale.up > 1:
            f = crops.scale.up
            d = _pool_valid(cons.depth[k], cons.keep[k], f)
            n = _pool_valid(cons.normal[k], cons.keep[k], f, unit=True)
        else:
            f = crops.scale.down
            d = _repeat(torch.where(cons.keep[k], cons.depth[k], torch.zeros_like(cons.depth[k])), f)
            n = _repeat(torch.where(cons.keep[k], cons.normal[k], torch.zeros_like(cons.normal[k])), f)
        fd[:, y0 : y0 + ch, x0 : x0 + cw] = d
        fn[:, y0 : y0 + ch, x0 : x0 + cw] = n
        full_depth.append(fd)
        full_normal.append(fn)
    return full_depth, full_normal


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
    scale (:func:`match_scale`), PatchMatch (:func:`~vadgs.mvs.patchmatch`), consistency
    (:func:`~vadgs.mvs.geometric_consistency`) and planar completion
    (:func:`~vadgs.mvs.complete_planar`), the pixels the Gaussians already explain, fusion
    (:func:`~vadgs.mvs.fuse_depth_maps`, one point per consistent unexplained pixel, thinned to one
    per cell of the point spacing by :func:`thin_points`), depth priors.

    Args:
        index: the scene's :class:`VisibilityIndex`.
        ref: the reference view.
        instance: the instance id (a track id for a moving object: matched in its own frame).
        config: :class:`ReconstructConfig`.
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
    """
    cfg = config or ReconstructConfig()
    inputs = index.inputs
    if not 0 <= ref < inputs.num_views:
        raise ValueError(f"ref: expected a view in [0, {inputs.num_views}), got {ref}")
    track = instance if instance in inputs.tracks else None
    if device is None and render_prior is not None:
        device = _renders(render_prior, ref)[0].device
    dev = torch.device(device) if device is not None else index.cameras.K.device
    empty3 = torch.zeros(0, 3, device=dev)

    def nothing(reason: str, views: list[int] | None = None) -> InstanceReconstruction:
        return InstanceReconstruction(
            empty3, empty3, empty3, torch.zeros(0, device=dev), track, views or [ref], [], [], reason
        )

    if int((index.instances(ref) == instance).sum()) < cfg.min_pixels:
        return nothing("instance_too_small_in_reference")
    frame = _instance_frame(index, ref, instance, track, cfg)  # 1. voxels and frame
    if isinstance(frame, str):
        return nothing(frame)
    sel = _select_supports(index, ref, instance, frame, cfg, generator)  # 2.
    group = [ref, *sel.views.tolist()]
    if len(group) < 2:
        return nothing(f"selection:{sel.reason}")
    crops = _crop_group(index, group, instance, track, cfg, dev)  # 3. crops and PatchMatch
    if isinstance(crops, str):
        return nothing(crops, group)
    w2c = frame.world_to_cam[group]
    depth_range = _depth_range(frame, w2c[0], cfg)
    w2c = w2c.to(dev)
    matched = _match(index, crops, group, w2c, depth_range, cfg, render_prior)
    planar = cfg.planar is not None and track is None  # a car is not planar
    cons = _consistent(matched, crops, group, w2c, planar, cfg, generator)  # 4.
    new = cons.keep & ~_explained(index, cons, crops, group, cfg, render_prior)  # 5. unexplained pixels
    fused = fuse_depth_maps(  # one point per such pixel, in the instance's frame
        cons.depth, matched.images, matched.K, matched.world_to_cam, cons.normal, new,
        FusionConfig(min_views=0, deduplicate=False),
    )  # fmt: skip
    seed_w2c, seed_K = matched.world_to_cam[fused.view_index], matched.K[fused.view_index]
    z_seed = (seed_w2c[:, 2, :3] * fused.points).sum(-1) + seed_w2c[:, 2, 3]
    points, normals, colors, spacing = fused.points, fused.normals, fused.colors, z_seed / seed_K[:, 0, 0]
    if (
        cfg.thin_points and points.shape[0]
    ):  # one point per cell of the scene resolution's spacing, or coarser
        spacing = spacing * (crops.scale.up * (cfg.thin_factor if crops.scale.down > 1 else 1.0))
        keep = thin_points(points, float(spacing.median()), None if occupied is None else occupied.to(dev))
        points, normals, colors, spacing = points[keep], normals[keep], colors[keep], spacing[keep]
    if points.shape[0] > cfg.max_points:
        g = generator or torch.Generator().manual_seed(0)
        sub = torch.randperm(points.shape[0], generator=g)[: cfg.max_points].to(dev)
        points, normals, colors, spacing = points[sub], normals[sub], colors[sub], spacing[sub]
    full_depth, full_normal = _depth_priors(cons, crops, index.cameras.image_size)  # 6.
    views = [group[i] for i in crops.members]
    reason = "ok" if points.shape[0] else ("explained" if bool(cons.keep.any()) else "no_consistent_pixels")
    return InstanceReconstruction(
        points, normals, colors, spacing, track, views, full_depth, full_normal, reason
    )
