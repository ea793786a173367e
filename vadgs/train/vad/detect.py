"""Incompleteness detection of an event (paper, Sec. 3.2, Eq. 4–5).

:func:`detect_view` runs :func:`~vadgs.train.vad.incomplete.find_incomplete` on one view's render
against the visibility index's voxel depth; :func:`detect` on many views, reusing the tests the
strategy made from the loop's own renders. The loop's renders are kept between events in a bounded
store (:func:`keep_render`, of maps made single-view by :func:`view_map`) and read back per event
by :class:`EventRenders`.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any

import torch

from vadgs.train.vad.incomplete import (
    IncompleteConfig,
    IncompleteInstances,
    find_incomplete,
    find_incomplete_ids,
)
from vadgs.train.vad.inputs import VisibilityInputs
from vadgs.train.vad.reconstruct import ViewRender
from vadgs.train.vad.state import compact_render, expand_render
from vadgs.train.vad.visibility import VisibilityIndex

__all__ = [
    "EventRenders",
    "detect",
    "detect_view",
    "keep_render",
    "observe_view",
    "view_map",
]


class EventRenders:
    """Renders of one event: the loop's own renders kept in the state, else rendered once."""

    def __init__(self, render: Callable[[int], ViewRender], kept: Mapping[int, tuple] | None = None) -> None:
        self.render, self.kept = render, kept or {}
        self.cache: dict[int, ViewRender] = {}
        self.rendered = 0

    def __call__(self, view: int) -> ViewRender:
        """The render of ``view``: kept, cached this event, or rendered now."""
        if view not in self.cache:
            if view in self.kept:
                self.cache[view] = ViewRender(*expand_render(self.kept[view]))
            else:
                self.cache[view] = self.render(view)
                self.rendered += 1
        return self.cache[view]


def view_map(x: torch.Tensor) -> torch.Tensor:
    """A single view's map as ``(C, H, W)``, detached (from ``(1, C, H, W)`` or ``(H, W)``)."""
    x = x.detach()
    return x[0] if x.dim() == 4 else x[None] if x.dim() == 2 else x


def keep_render(store: dict, view: int, render: ViewRender, max_bytes: int) -> None:
    """Keep a view's render (:func:`compact_render`) in ``store``, the oldest dropped beyond ``max_bytes``."""
    store.pop(view, None)
    if max_bytes <= 0:
        return
    store[view] = compact_render(*render)
    total = sum(sum(x.numel() * x.element_size() for x in r) for r in store.values())
    while total > max_bytes and len(store) > 1:
        oldest = next(iter(store))
        total -= sum(x.numel() * x.element_size() for x in store.pop(oldest))


def detect_view(
    index: VisibilityIndex, view: int, depth: torch.Tensor, alpha: torch.Tensor, config: IncompleteConfig
) -> tuple[torch.Tensor, ...]:
    """The incompleteness test of one view, on the render's device.

    The view's instance map and voxel depth move to the render (the render does not move).
    Returns the fields of its :class:`~vadgs.train.vad.incomplete.IncompleteInstances` (``view`` = 0).
    """
    dev = depth.device
    h, w = depth.shape[-2:]  # the view's own size (the index's maps may be padded)
    d, _ = index.voxel_depth(view)
    rows = find_incomplete(
        index.instances(view)[None, :h, :w].to(dev),
        d[None, :, :h, :w].to(dev),
        depth.detach().reshape(1, 1, *depth.shape[-2:]),
        alpha.detach().reshape(1, 1, *alpha.shape[-2:]),
        config,
    )
    return tuple(rows)


@torch.no_grad()
def detect(
    index: VisibilityIndex,
    views: list[int],
    render: Callable[[int], ViewRender],
    tests: Mapping[int, tuple[torch.Tensor, ...]],
    incomplete: IncompleteConfig,
) -> tuple[IncompleteInstances, list[int]]:
    """The incompleteness test of ``views`` (``VisibilityAwareDensification.detect``'s body).

    A view in ``tests`` (the fields of its one-view test, from the loop's render; with a ninth,
    the ``tested`` mask of :func:`~vadgs.train.vad.incomplete.find_incomplete_ids`, whose rows it
    selects here) is not rendered again; the others are rendered with ``render``. Returns
    ``(rows, views)``, ``rows.view`` indexing ``views``, on the device of the first view's test.
    """
    parts = []
    for k, v in enumerate(views):
        if v in tests:
            fields = tests[v]
            if len(fields) == len(IncompleteInstances._fields) + 1:  # observe_view's: one row per id
                keep = torch.nonzero(fields[-1]).squeeze(1)
                fields = tuple(f[keep] for f in fields[:-1])
        else:
            out = render(v)
            fields = detect_view(index, v, out.depth, out.alpha, incomplete)
        one = IncompleteInstances(*fields)
        parts.append(one._replace(view=torch.full_like(one.view, k)))
    dev = parts[0].view.device
    rows = IncompleteInstances(
        *(torch.cat([getattr(p, f).to(dev) for p in parts]) for f in IncompleteInstances._fields)
    )
    return rows, views


def observe_view(
    state: dict[str, Any],
    info: Mapping[str, Any],
    index: VisibilityIndex,
    inputs: VisibilityInputs,
    incomplete: IncompleteConfig,
    max_bytes: int,
    num_ids: dict[int, int] | None = None,
) -> None:
    """Test the view a loop just trained from its own render in ``info``, and keep that render.

    ``info["view"]`` and ``info["raster"]`` with ``depth`` / ``alpha`` (/ ``normals``), as vadgs's
    trainer passes, or ``info["depth"]`` / ``info["alpha"]``: the view's test
    (:func:`detect_view`) goes to ``state["vad_tests"]`` and its render to
    ``state["vad_renders"]`` (:func:`keep_render`, up to ``max_bytes``), so that the next event
    does not render it again. Nothing is done without a render, or for a render of another size
    than the view's (a crop or another scale, e.g. gsplat's ``patch_size``). The test is
    :func:`~vadgs.train.vad.incomplete.find_incomplete_ids`, without a read by the host when
    ``num_ids`` (view -> one more than its largest instance id, filled here at a view's first
    test) is kept between calls; :func:`detect` selects its rows at the event.
    """
    view = info.get("view")
    if view is None:
        return
    raster = info.get("raster")
    src = raster if raster is not None else info
    get = (lambda k: getattr(src, k, None)) if raster is not None else src.get
    depth, alpha, normals = get("depth"), get("alpha"), get("normals")
    if depth is None or alpha is None:
        return
    view = int(view)
    depth, alpha = view_map(depth), view_map(alpha)
    if tuple(depth.shape[-2:]) != tuple(inputs.size(view)):
        return
    num_ids = {} if num_ids is None else num_ids
    h, w = depth.shape[-2:]
    ins = index.instances(view)[None, :h, :w]
    if view not in num_ids:
        num_ids[view] = int(ins.max()) + 1 if ins.numel() else 1
    dev = depth.device
    vox, _ = index.voxel_depth(view)
    rows, tested = find_incomplete_ids(
        ins.to(dev), vox[None, :, :h, :w].to(dev), depth.reshape(1, 1, h, w), alpha.reshape(1, 1, h, w),
        num_ids[view], incomplete,
    )  # fmt: skip
    state.setdefault("vad_tests", {})[view] = (*rows, tested)
    normals = torch.zeros(3, *depth.shape[-2:]).to(depth) if normals is None else view_map(normals)
    keep_render(state.setdefault("vad_renders", {}), view, ViewRender(depth, alpha, normals), max_bytes)
