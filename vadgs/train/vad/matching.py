"""Step 3b of :func:`~vadgs.train.vad.reconstruct.reconstruct_instance`: the pairs' PatchMatch, batched.

An event plans each of its (instance, reference) pairs (:func:`~vadgs.train.vad.reconstruct.plan_matches`:
a :class:`MatchPlan`), then matches them all here, in as few
:func:`~vadgs.mvs.patchmatch` calls as their crop sizes allow (:func:`match_plans`: every member of
every plan one reference of a call, crops padded to the largest of their call), and finishes each
(:func:`~vadgs.train.vad.reconstruct.finish_match`). :func:`match_work` is the matching's cost, in
pixel-sweeps (the unit of the event's ``work_budget``).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING, Any, NamedTuple

import torch

from vadgs.checks import checking
from vadgs.mvs.patchmatch import PatchMatchConfig, PatchMatchResult, patchmatch
from vadgs.train.vad import reconstruct_config
from vadgs.train.vad.crops import Crops, MatchedCrops, render_maps, to_scale

if TYPE_CHECKING:
    from vadgs.train.vad.reconstruct_config import ReconstructConfig
    from vadgs.train.vad.visibility import VisibilityIndex

__all__ = [
    "MAX_CALL_PIXEL_VIEWS",
    "MatchInputs",
    "MatchPlan",
    "match_batches",
    "match_plans",
    "match_work",
]


class MatchPlan(NamedTuple):
    """An (instance, reference) pair selected and cropped, ready for PatchMatch.

    Made by :func:`~vadgs.train.vad.reconstruct.plan_matches`, matched by :func:`match_plans`.

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
    index: VisibilityIndex, plan: MatchPlan, render_prior: Callable[[int], Any] | None
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
    render_prior: Callable[[int], Any] | None = None,
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
    render_prior: Callable[[int], Any] | None,
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


def match_work(masks: torch.Tensor | float, sources: int, config: PatchMatchConfig) -> float:
    """PatchMatch's work on the given reference masks, in pixel-sweeps (machine-independent).

    Reference pixels scored (the ``True`` pixels of ``masks``, at the matching scale, or their
    count when the caller has it: no read by the host) × source views × sweeps, a sweep at a
    pyramid level ``l`` levels coarser counting ``4^-l`` of one at the matching scale:
    ``iterations`` at the coarsest level and ``fine_iterations`` at each finer one
    (:class:`~vadgs.mvs.PatchMatchConfig`). An exact function of the crops (no timing): the unit of
    the VAD-GS event's ``work_budget``.

    Example:
        >>> from vadgs.mvs import PatchMatchConfig
        >>> m = torch.ones(1, 1, 10, 20, dtype=torch.bool)  # 200 pixels, 4 sources
        >>> match_work(m, 4, PatchMatchConfig(iterations=3, pyramid_levels=2, fine_iterations=1))
        1400.0
        >>> match_work(200, 4, PatchMatchConfig(iterations=3, pyramid_levels=2, fine_iterations=1))
        1400.0
    """
    pixels = float(masks.sum()) if isinstance(masks, torch.Tensor) else float(masks)
    levels = max(int(config.pyramid_levels), 1)
    sweeps = config.iterations * 4.0 ** -(levels - 1)
    sweeps += config.fine_iterations * sum(4.0**-k for k in range(levels - 1))
    return pixels * sources * sweeps
