r"""Find instances with incomplete geometry (paper, "Voxel-Based Visibility Reasoning").

For each instance (a mask of an instance map) of each view, the depth rendered from the Gaussians
is compared with the depth of the voxel z-buffer. The instance is flagged for re-initialisation
when

- the rendered depth is absent or significantly larger than the voxel depth: the median over
  the instance's pixels that have a voxel depth of :math:`z_\text{render} / z_\text{voxel}`
  exceeds ``depth_ratio`` (1.1 in the paper; pixels with no rendered depth count as
  :math:`+\infty`), or
- more than ``low_alpha_fraction`` (25%) of its pixels have an accumulated opacity below
  ``alpha_threshold`` (0.7).

Rendered depth consistently *smaller* than the voxel depth is not flagged: it means completed
geometry in front of the voxels, or redundancy that opacity can resolve.

Given the voxel index map and each voxel's instance label (:func:`~vadgs.geometry.voxel_labels`),
:func:`find_incomplete` also reports the share of an instance's pixels that map to voxels of
*other* instances (``foreign``: the z-buffer sees through it to what lies behind), as a diagnostic;
it flags nothing.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import torch

from vadgs.checks import Checked, check_shape, checked, float_field, int_field, ints_field

__all__ = ["IncompleteConfig", "IncompleteInstances", "find_incomplete", "find_incomplete_ids"]


@dataclass(frozen=True)
class IncompleteConfig(Checked):
    """Thresholds of :func:`find_incomplete` (paper values by default).

    Attributes:
        depth_ratio: flag when the median rendered/voxel depth ratio exceeds this.
        alpha_threshold: a pixel is "transparent" below this accumulated opacity.
        low_alpha_fraction: flag when more than this share of the instance's pixels is transparent.
        min_pixels: instances with fewer pixels in a view are skipped.
        min_alpha_for_depth: rendered depth counts as absent where alpha is below this.
        ignore_ids: instance ids never tested (0 = sky / none).
    """

    depth_ratio: float = checked(1.1, float_field(0, lo_open=True))
    alpha_threshold: float = checked(0.7, float_field(0, 1))
    low_alpha_fraction: float = checked(0.25, float_field(0, 1))
    min_pixels: int = checked(20, int_field(0))
    min_alpha_for_depth: float = checked(0.05, float_field(0, 1))
    ignore_ids: tuple[int, ...] = checked((0,), ints_field("instance ids"))


class IncompleteInstances(NamedTuple):
    """One row per (view, instance) tested.

    Attributes:
        view: ``(R,)`` int64 batch index of the view.
        instance: ``(R,)`` int64 instance id.
        flagged: ``(R,)`` bool.
        depth_ratio: ``(R,)`` median rendered/voxel depth ratio (``nan`` without voxel depth,
            ``inf`` when nothing is rendered there).
        low_alpha: ``(R,)`` share of pixels with alpha below the threshold.
        foreign: ``(R,)`` share of voxel-covered pixels mapping to other instances' voxels
            (``nan`` without labels; a diagnostic, not a criterion).
        pixels: ``(R,)`` int64 pixel count of the instance.
        voxel_pixels: ``(R,)`` int64 pixels that have a voxel depth.
    """

    view: torch.Tensor
    instance: torch.Tensor
    flagged: torch.Tensor
    depth_ratio: torch.Tensor
    low_alpha: torch.Tensor
    foreign: torch.Tensor
    pixels: torch.Tensor
    voxel_pixels: torch.Tensor


def _segment_median(values: torch.Tensor, segment: torch.Tensor, num: int) -> torch.Tensor:
    """Lower median of ``values`` per segment id in ``[0, num)``; nan for empty segments."""
    out = torch.full((num,), float("nan"), dtype=values.dtype, device=values.device)
    if values.numel() == 0:
        return out
    # sort by (segment, value): values are sorted within each segment
    order = torch.argsort(values, stable=True)
    order = order[torch.argsort(segment[order], stable=True)]
    seg_sorted = segment[order]
    counts = torch.bincount(seg_sorted, minlength=num)
    starts = counts.cumsum(0) - counts
    has = counts > 0
    mid = starts[has] + (counts[has] - 1) // 2
    out[has] = values[order][mid]
    return out


def find_incomplete(
    instances: torch.Tensor,
    voxel_depth: torch.Tensor,
    rendered_depth: torch.Tensor,
    rendered_alpha: torch.Tensor,
    config: IncompleteConfig | None = None,
    voxel_index: torch.Tensor | None = None,
    voxel_labels: torch.Tensor | None = None,
) -> IncompleteInstances:
    """Flag the instances whose rendered geometry is absent, behind the voxels or transparent.

    Not differentiable (a test, run under ``torch.no_grad()``); vectorised over all views and
    instances at once.

    Args:
        instances: ``(B, H, W)`` int64 instance ids (0 = none).
        voxel_depth: ``(B, 1, H, W)`` voxel z-buffer depth, 0 where empty.
        rendered_depth: ``(B, 1, H, W)`` depth rendered from the Gaussians (expected or median).
        rendered_alpha: ``(B, 1, H, W)`` accumulated opacity.
        config: :class:`IncompleteConfig`.
        voxel_index: ``(B, H, W)`` voxel index map (needed with ``voxel_labels``).
        voxel_labels: ``(M,)`` int64 instance label of each voxel: with ``voxel_index``, the
            ``foreign`` share is reported (it flags nothing).

    Returns:
        :class:`IncompleteInstances`, rows sorted by (view, instance).

    Example:
        >>> ins = torch.zeros(1, 8, 8, dtype=torch.long); ins[0, :4] = 5; ins[0, 4:] = 6
        >>> vox = torch.full((1, 1, 8, 8), 10.0)
        >>> ren = vox.clone(); ren[0, 0, 4:] = 14.0  # instance 6 rendered far behind its voxels
        >>> out = find_incomplete(ins, vox, ren, torch.ones(1, 1, 8, 8))
        >>> out.instance.tolist(), out.flagged.tolist(), out.depth_ratio.tolist()
        ([5, 6], [False, True], [1.0, 1.399999976158142])
    """
    cfg = config or IncompleteConfig()
    dims = check_shape(instances, "instances", ("B", "H", "W"))
    for name, t in (
        ("voxel_depth", voxel_depth),
        ("rendered_depth", rendered_depth),
        ("rendered_alpha", rendered_alpha),
    ):
        check_shape(t, name, ("B", 1, "H", "W"), dims)
    if (voxel_labels is None) != (voxel_index is None):
        raise ValueError("voxel_index and voxel_labels: give both or neither")
    if voxel_index is not None:
        check_shape(voxel_index, "voxel_index", ("B", "H", "W"), dims)
    with torch.no_grad():
        b = dims["B"]
        ins = instances.reshape(b, -1)
        keep = ~torch.isin(ins, torch.tensor(cfg.ignore_ids, device=ins.device, dtype=ins.dtype))
        # one segment per (view, instance) pair present
        view_of = torch.arange(b, device=ins.device)[:, None].expand_as(ins)
        max_id = int(ins.max()) + 1 if ins.numel() else 1
        key_all = view_of * max_id + ins
        kept = torch.nonzero(keep.reshape(-1)).squeeze(1)  # one read for the kept pixels' maps
        keys, seg = torch.unique(key_all.reshape(-1)[kept], return_inverse=True)
        r = keys.numel()
        pixels = torch.bincount(seg, minlength=r)
        alpha = rendered_alpha.reshape(-1)[kept]
        vd = voxel_depth.reshape(-1)[kept]
        rd = rendered_depth.reshape(-1)[kept]
        low = torch.bincount(seg, weights=(alpha < cfg.alpha_threshold).double(), minlength=r) / pixels.clamp(
            min=1
        )
        has_vox = vd > 0
        voxel_pixels = torch.bincount(seg[has_vox], minlength=r)
        absent = (alpha < cfg.min_alpha_for_depth) | (rd <= 0)
        ratio = torch.where(absent, torch.full_like(rd, float("inf")), rd / vd.clamp(min=1e-12))
        med = _segment_median(ratio[has_vox].double(), seg[has_vox], r)
        foreign = torch.full((r,), float("nan"), dtype=torch.float64, device=ins.device)
        if voxel_labels is not None:
            vi = voxel_index.reshape(-1)[kept]  # type: ignore[union-attr]
            covered = vi >= 0
            lab = voxel_labels.to(ins.device)[vi[covered]]
            other = (lab != ins.reshape(-1)[kept][covered]).double()
            cnt = torch.bincount(seg[covered], minlength=r)
            foreign = torch.where(
                cnt > 0, torch.bincount(seg[covered], weights=other, minlength=r) / cnt.clamp(min=1), foreign
            )
        flagged = (med > cfg.depth_ratio) | (low > cfg.low_alpha_fraction)
        big = pixels >= cfg.min_pixels
        flagged &= big
        sel = torch.nonzero(big).squeeze(1)  # one read for the rows' fields
        return IncompleteInstances(
            view=(keys // max_id)[sel],
            instance=(keys % max_id)[sel],
            flagged=flagged[sel],
            depth_ratio=med.to(rendered_depth.dtype)[sel],
            low_alpha=low.to(rendered_depth.dtype)[sel],
            foreign=foreign.to(rendered_depth.dtype)[sel],
            pixels=pixels[sel],
            voxel_pixels=voxel_pixels[sel],
        )


def find_incomplete_ids(
    instances: torch.Tensor,
    voxel_depth: torch.Tensor,
    rendered_depth: torch.Tensor,
    rendered_alpha: torch.Tensor,
    num_ids: int,
    config: IncompleteConfig | None = None,
) -> tuple[IncompleteInstances, torch.Tensor]:
    """:func:`find_incomplete` of one view in sizes known beforehand: one row per instance id.

    Every tensor it makes has a size fixed by the view's size and ``num_ids``, so that nothing is
    read by the host (a synchronisation each on a GPU): for a training step's own render, tested
    every step (:func:`~vadgs.train.vad.detect.observe_view`). Returns ``(rows, tested)``: row
    ``i`` is instance id ``i`` of ``[0, num_ids)``, and ``rows`` masked with ``tested`` (bool
    ``(num_ids,)``) are :func:`find_incomplete`'s rows without voxel labels, value for value (the
    same sums and the same median element).

    Args:
        instances: ``(1, H, W)`` int64 instance ids in ``[0, num_ids)``.
        voxel_depth: ``(1, 1, H, W)``.
        rendered_depth: ``(1, 1, H, W)``.
        rendered_alpha: ``(1, 1, H, W)``.
        num_ids: more than the largest id of ``instances`` (the view's, read once and kept).
        config: :class:`IncompleteConfig`.

    Example:
        >>> ins = torch.zeros(1, 8, 8, dtype=torch.long); ins[0, :4] = 5; ins[0, 4:] = 6
        >>> vox = torch.full((1, 1, 8, 8), 10.0)
        >>> ren = vox.clone(); ren[0, 0, 4:] = 14.0
        >>> rows, tested = find_incomplete_ids(ins, vox, ren, torch.ones(1, 1, 8, 8), 7)
        >>> rows.instance[tested].tolist(), rows.flagged[tested].tolist()
        ([5, 6], [False, True])
    """
    cfg = config or IncompleteConfig()
    dims = check_shape(instances, "instances", (1, "H", "W"))
    for name, t in (
        ("voxel_depth", voxel_depth),
        ("rendered_depth", rendered_depth),
        ("rendered_alpha", rendered_alpha),
    ):
        check_shape(t, name, (1, 1, "H", "W"), dims)
    with torch.no_grad():
        ins = instances.reshape(-1)
        dev = ins.device
        m = num_ids
        keep = ~torch.isin(ins, torch.tensor(cfg.ignore_ids, device=dev, dtype=ins.dtype))
        seg = torch.where(keep, ins, m)  # the pixels left out: segment m, after every id
        alpha = rendered_alpha.reshape(-1)
        vd = voxel_depth.reshape(-1)
        rd = rendered_depth.reshape(-1)
        pixels = torch.bincount(seg, minlength=m + 1)[:m]
        low_n = torch.bincount(seg, weights=(alpha < cfg.alpha_threshold).double(), minlength=m + 1)[:m]
        low = low_n / pixels.clamp(min=1)
        has_vox = vd > 0
        seg_vox = torch.where(has_vox, seg, m)
        counts = torch.bincount(seg_vox, minlength=m + 1)
        voxel_pixels = counts[:m]
        absent = (alpha < cfg.min_alpha_for_depth) | (rd <= 0)
        ratio = torch.where(absent, torch.full_like(rd, float("inf")), rd / vd.clamp(min=1e-12)).double()
        # _segment_median's sort (by value, then stably by segment) of every pixel, the pixels
        # without a voxel depth or left out in segment m, last
        order = torch.argsort(ratio, stable=True)
        order = order[torch.argsort(seg_vox[order], stable=True)]
        starts = counts.cumsum(0) - counts
        mid = (starts[:m] + (voxel_pixels - 1).clamp(min=0) // 2).clamp(max=max(ratio.numel() - 1, 0))
        med = ratio[order][mid] if ratio.numel() else torch.zeros(m, dtype=ratio.dtype, device=dev)
        med = torch.where(voxel_pixels > 0, med, float("nan"))
        flagged = ((med > cfg.depth_ratio) | (low > cfg.low_alpha_fraction)) & (pixels >= cfg.min_pixels)
        tested = (pixels > 0) & (pixels >= cfg.min_pixels)
        dtype = rendered_depth.dtype
        rows = IncompleteInstances(
            view=torch.zeros(m, dtype=torch.long, device=dev),
            instance=torch.arange(m, device=dev),
            flagged=flagged,
            depth_ratio=med.to(dtype),
            low_alpha=low.to(dtype),
            foreign=torch.full((m,), float("nan"), dtype=dtype, device=dev),
            pixels=pixels,
            voxel_pixels=voxel_pixels,
        )
        return rows, tested
