"""An instance's crops at its matching scale: step 3a of its multi-view stereo (paper, Sec. 4.3).

:func:`~vadgs.train.vad.reconstruct.reconstruct_instance` matches an instance on crops around it in
each group view, at a scale of its own (:func:`match_scale`): finer than the scene's resolution
for small instances (a sign), coarser for large ones (a facade). :func:`crop_group` makes the
crops (:class:`Crops`, sources restricted to each view's :func:`matching_region`: the paper's
static or dynamic region), which PatchMatch turns into :class:`MatchedCrops`; :func:`render_maps`
reads the Gaussians' render of a view (the matching's initialisation and the test of what is
already explained); :func:`to_scale` resamples a map from the scene's resolution to the matching
scale (:func:`~vadgs.geometry.resample.repeat` or :func:`~vadgs.geometry.resample.pool_valid`, as
the scale asks).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple

import torch
import torch.nn.functional as F

from vadgs.geometry.camera import scale_intrinsics
from vadgs.geometry.resample import pool_mask, pool_valid, repeat
from vadgs.mvs.patchmatch import PatchMatchResult
from vadgs.train.vad.reconstruct_config import ReconstructConfig
from vadgs.train.vad.visibility import VisibilityIndex

__all__ = [
    "Crops",
    "MatchScale",
    "MatchedCrops",
    "crop_group",
    "match_scale",
    "matching_region",
    "render_maps",
    "to_scale",
]


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


def _mask_boxes(masks: Sequence[torch.Tensor]) -> tuple[list[int], list[tuple[int, int, int, int]]]:
    """Each mask's pixel count and bounding box ``(y_min, y_max, x_min, x_max)``, in one host read.

    A mask without pixels gets the box ``(0, -1, 0, -1)``.
    """
    m = torch.stack(list(masks))  # (M, H, W): the masks of one index share its size
    rows, cols = m.any(-1), m.any(-2)  # (M, H), (M, W)
    hh, ww = rows.shape[-1], cols.shape[-1]
    stats = torch.stack(
        [
            m.sum((-2, -1)),
            rows.int().argmax(-1),
            hh - 1 - rows.flip(-1).int().argmax(-1),
            cols.int().argmax(-1),
            ww - 1 - cols.flip(-1).int().argmax(-1),
        ],
        1,
    ).tolist()
    sizes = [s[0] for s in stats]
    boxes = [(s[1], s[2], s[3], s[4]) if s[0] else (0, -1, 0, -1) for s in stats]
    return sizes, boxes


def _crops(
    boxes: Sequence[tuple[int, int, int, int]], margin: int, size: tuple[int, int], max_crop: int
) -> tuple[list[tuple[int, int]], int, int]:
    """One crop size for all masks (their :func:`_mask_boxes`) and each crop's top-left corner.

    The size is the largest bounding box plus margin (capped); each crop is centred on its mask's
    box and clipped to the image.
    """
    hh, ww = size
    centres, hs, ws = [], [], []
    for y_min, y_max, x_min, x_max in boxes:
        centres.append(((y_min + y_max) // 2, (x_min + x_max) // 2))
        hs.append(y_max - y_min + 1 + 2 * margin)
        ws.append(x_max - x_min + 1 + 2 * margin)
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


def to_scale(x: torch.Tensor, valid: torch.Tensor, scale: MatchScale, unit: bool = False) -> torch.Tensor:
    """A scene-resolution map ``(C, H, W)`` at the matching scale (valid-pixel means when coarser)."""
    if scale.up > 1:
        return repeat(torch.where(valid, x, torch.zeros_like(x)), scale.up)
    return pool_valid(x, valid, scale.down, unit)


def render_maps(
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


def matching_region(index: VisibilityIndex, view: int, instance: int, track: int | None) -> torch.Tensor:
    """Where a view's pixels may match an instance: the static or the dynamic region (paper, Sec. 4.3).

    The paper restricts patch matching "within either static or dynamic regions across all relevant
    views": a static instance is matched against the view's static pixels (no moving object's,
    and none outside the view's valid pixels), a moving object (``track`` given) only against its
    own pixels, in its own frame (:func:`~vadgs.train.vad.reconstruct.instance_frame`).

    Args:
        index: the visibility index (its instance maps and valid pixels).
        view: the view.
        instance: the instance's id in the instance maps.
        track: the instance's track id when it moves, else None.

    Returns:
        ``(H, W)`` bool on the index's device.
    """
    ins = index.instances(view)
    if track is not None:
        return ins == instance
    moving = torch.tensor(sorted(index.inputs.tracks), dtype=ins.dtype, device=ins.device)
    return ~torch.isin(ins, moving) & index.valid(view)


class Crops(NamedTuple):
    """Step 3's input: the group's images and masks cropped around the instance, at the matching scale."""

    members: list[int]  # group positions whose instance mask is large enough to be a reference
    images: torch.Tensor  # (G, 3, h, w) full images of the group at the matching scale
    masks: list[torch.Tensor]  # per group view (h, w): the instance
    regions: torch.Tensor  # (G, 1, h, w): where sources may match (matching_region)
    K: torch.Tensor  # (G, 3, 3) at the matching scale
    corners: list[tuple[int, int]]  # per member: top-left of its crop, at the matching scale
    size: tuple[int, int]  # crop (ch, cw) at the matching scale
    corners_lo: list[tuple[int, int]]  # the same at the scene's resolution
    size_lo: tuple[int, int]
    scale: MatchScale


def crop_group(
    index: VisibilityIndex,
    group: list[int],
    instance: int,
    track: int | None,
    cfg: ReconstructConfig,
    device: torch.device,
) -> Crops | str:
    """Step 3a: crops around the instance in each group view, at its matching scale (:func:`match_scale`).

    Sources match only inside their :func:`matching_region`: static pixels for a static instance,
    the object's own pixels for a moving one. The group's images, masks and intrinsics move to
    ``device`` (where the matching runs), once.
    """
    inputs = index.inputs
    h, w = index.cameras.image_size
    masks = [index.instances(v) == instance for v in group]
    sizes, boxes = _mask_boxes(masks)
    members = [i for i, n in enumerate(sizes) if n >= cfg.min_pixels]
    if len(members) < 2:
        return "instance_seen_in_fewer_than_two_group_views"
    corners, ch, cw = _crops([boxes[i] for i in members], cfg.margin, (h, w), cfg.max_crop)
    native = inputs.native_factor  # the files' resolution
    scale = match_scale(max(sizes[i] for i in members), (ch, cw), native, cfg)
    if scale.down > 1:
        corners, ch, cw = _align_crops(corners, ch, cw, scale.down, (h, w))

    regions = torch.stack([matching_region(index, v, instance, track) for v in group])[:, None]
    K = index.cameras.K[group]
    corners_lo, size_lo = corners, (ch, cw)
    if scale.up > 1:
        f = scale.up
        masks = [repeat(m, f) for m in masks]
        regions = repeat(regions, f)
        corners, ch, cw = [(y0 * f, x0 * f) for y0, x0 in corners], ch * f, cw * f
        K = scale_intrinsics(K, f)
        images = torch.stack([index.image(v, f) for v in group])
    else:
        f = scale.down
        images = torch.stack([index.image(v) for v in group])
        if f > 1:
            masks = [pool_mask(m, f) for m in masks]
            regions = pool_mask(regions, f)
            corners, ch, cw = [(y0 // f, x0 // f) for y0, x0 in corners], ch // f, cw // f
            K = scale_intrinsics(K, 1.0 / f)
            images = F.avg_pool2d(images, f)
    images, regions, K = images.to(device), regions.to(device), K.to(device)
    masks = [m.to(device) for m in masks]
    return Crops(members, images, masks, regions, K, corners, (ch, cw), corners_lo, size_lo, scale)


class MatchedCrops(NamedTuple):
    """Step 3b's result: PatchMatch of each member's crop, with that crop's inputs."""

    result: PatchMatchResult
    images: torch.Tensor  # (b, 3, ch, cw) the members' crops
    masks: torch.Tensor  # (b, 1, ch, cw)
    K: torch.Tensor  # (b, 3, 3) of the crops
    world_to_cam: torch.Tensor  # (b, 4, 4)
