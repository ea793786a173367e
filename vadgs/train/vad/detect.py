"""Incompleteness detection of an event (paper, Sec. 4.1; thresholds: Sec. 5.2).

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
    "detect_kept",
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


def keep_render(
    store: dict,
    view: int,
    render: ViewRender,
    max_bytes: int,
    on_drop: Callable[[int, tuple], None] | None = None,
) -> None:
    """Keep a view's render (:func:`compact_render`) in ``store``, the oldest dropped beyond ``max_bytes``.

    ``on_drop(view, kept)`` is called with each render dropped for room (not with ``view``'s own
    earlier render, which the new one replaces).
    """
    store.pop(view, None)
    if max_bytes <= 0:
        return
    store[view] = compact_render(*render)
    total = sum(sum(x.numel() * x.element_size() for x in r) for r in store.values())
    while total > max_bytes and len(store) > 1:
        oldest = next(iter(store))
        kept = store.pop(oldest)
        total -= sum(x.numel() * x.element_size() for x in kept)
        if on_drop is not None:
            on_drop(oldest, kept)


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


#: pixels of one batched test of kept renders at the event (:func:`detect`): about 20 bytes a pixel
#: in flight (the instance map, the voxel depth and the render's depth and opacity, expanded)
TEST_BATCH_PIXELS = 2**23


@torch.no_grad()
def detect(
    index: VisibilityIndex,
    views: list[int],
    render: Callable[[int], ViewRender],
    tests: Mapping[int, tuple[torch.Tensor, ...]],
    incomplete: IncompleteConfig,
) -> tuple[IncompleteInstances, list[int]]:
    """The incompleteness test of ``views`` (``VisibilityAwareDensification.detect``'s body).

    A view in ``tests`` is not rendered again: its entry is the fields of its one-view test (with
    a ninth, the ``tested`` mask of :func:`~vadgs.train.vad.incomplete.find_incomplete_ids`,
    whose rows it selects here), or empty (``()``, :func:`observe_view`'s) when the loop's render
    of the view is kept in ``render.kept`` (``render`` an :class:`EventRenders`): those kept
    renders are tested here, batched (the views of one size together, up to
    :data:`TEST_BATCH_PIXELS` pixels a call). The other views are rendered with ``render``.
    Returns ``(rows, views)``, ``rows.view`` indexing ``views``, rows sorted by (view, instance),
    on the device of the first view's test.
    """
    kept = render.kept if isinstance(render, EventRenders) else {}
    parts: list[IncompleteInstances] = []
    batches: dict[tuple[int, int], list[int]] = {}  # (H, W) -> positions k of kept views to test
    for k, v in enumerate(views):
        fields = tests.get(v)
        if fields is not None and len(fields) == 0 and v in kept:
            batches.setdefault(tuple(kept[v][0].shape[-2:]), []).append(k)
            continue
        if fields:
            if len(fields) == len(IncompleteInstances._fields) + 1:  # find_incomplete_ids': one row per id
                keep = torch.nonzero(fields[-1]).squeeze(1)
                fields = tuple(f[keep] for f in fields[:-1])
        else:
            out = render(v)
            fields = detect_view(index, v, out.depth, out.alpha, incomplete)
        one = IncompleteInstances(*fields)
        parts.append(one._replace(view=torch.full_like(one.view, k)))
    for (h, w), ks in batches.items():
        per = max(1, TEST_BATCH_PIXELS // max(h * w, 1))
        for i in range(0, len(ks), per):
            chunk = ks[i : i + per]
            rows = detect_kept([views[k] for k in chunk], index, kept, incomplete)
            parts.append(rows._replace(view=torch.tensor(chunk, device=rows.view.device)[rows.view]))
    dev = parts[0].view.device
    rows = IncompleteInstances(
        *(torch.cat([getattr(p, f).to(dev) for p in parts]) for f in IncompleteInstances._fields)
    )
    if batches and len(parts) > 1:  # (view, instance) order: each part's rows are of its views, sorted
        rows = IncompleteInstances(*(f[torch.argsort(rows.view, stable=True)] for f in rows))
    return rows, views


def _kept_depth_alpha(kept: tuple[torch.Tensor, ...]) -> tuple[torch.Tensor, torch.Tensor]:
    """The ``float32`` depth and opacity of a kept render, as :func:`expand_render` gives them."""
    depth, alpha = kept[0], kept[1]
    return depth.float(), (alpha.float() / 255 if alpha.dtype == torch.uint8 else alpha.float())


def detect_kept(
    views: list[int], index: VisibilityIndex, kept: Mapping[int, tuple], incomplete: IncompleteConfig
) -> IncompleteInstances:
    """The incompleteness test of views from their kept renders (:func:`compact_render`), batched.

    One :func:`~vadgs.train.vad.incomplete.find_incomplete` call on the renders expanded as
    :func:`expand_render` expands them (depth and opacity only), for views of one size; rows'
    ``view`` indexes ``views``. On the renders' device.
    """
    d0 = kept[views[0]][0]
    h, w = d0.shape[-2:]
    dev = d0.device
    depth, alpha = (torch.stack(x) for x in zip(*(_kept_depth_alpha(kept[v]) for v in views)))
    ins = torch.stack([index.instances(v)[:h, :w].to(dev) for v in views])
    vox = torch.stack([index.voxel_depth(v)[0][:, :h, :w].to(dev) for v in views])
    return find_incomplete(ins, vox, depth, alpha, incomplete)


def observe_view(
    state: dict[str, Any],
    info: Mapping[str, Any],
    index: VisibilityIndex,
    inputs: VisibilityInputs,
    incomplete: IncompleteConfig,
    max_bytes: int,
    num_ids: dict[int, int] | None = None,
) -> None:
    """Keep the render of the view a loop just trained (in ``info``) for the next event's test.

    ``info["view"]`` and ``info["raster"]`` with ``depth`` / ``alpha`` (/ ``normals``), as vadgs's
    trainer passes, or ``info["depth"]`` / ``info["alpha"]``: the render goes to
    ``state["vad_renders"]`` (:func:`keep_render`, up to ``max_bytes``) and the view to
    ``state["vad_tests"]`` with an empty entry: the event tests the kept renders together
    (:func:`detect`), none is tested on the step. A render dropped for room is tested when it is
    dropped, from its kept form as the event would (its entry then holds the test's fields), and
    with ``max_bytes`` 0 the step's own render is tested at once; both with
    :func:`~vadgs.train.vad.incomplete.find_incomplete_ids`, without a read by the host when
    ``num_ids`` (view -> one more than its largest instance id, filled here at a view's first
    such test) is kept between calls. Nothing is done without a render, or for a render of
    another size than the view's (a crop or another scale, e.g. gsplat's ``patch_size``).
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
    tests = state.setdefault("vad_tests", {})

    def test(v: int, d: torch.Tensor, a: torch.Tensor) -> None:
        h, w = d.shape[-2:]
        ins = index.instances(v)[None, :h, :w]
        if v not in num_ids:
            num_ids[v] = int(ins.max()) + 1 if ins.numel() else 1
        dev = d.device
        vox, _ = index.voxel_depth(v)
        rows, tested = find_incomplete_ids(
            ins.to(dev), vox[None, :, :h, :w].to(dev), d.reshape(1, 1, h, w), a.reshape(1, 1, h, w),
            num_ids[v], incomplete,
        )  # fmt: skip
        tests[v] = (*rows, tested)

    def dropped(v: int, kept: tuple) -> None:
        if v in tests and len(tests[v]) == 0:  # its test was left to the event: made now
            test(v, *_kept_depth_alpha(kept))

    store = state.setdefault("vad_renders", {})
    if max_bytes <= 0:
        store.pop(view, None)
        test(view, depth, alpha)
        return
    normals = torch.zeros(3, *depth.shape[-2:]).to(depth) if normals is None else view_map(normals)
    keep_render(store, view, ViewRender(depth, alpha, normals), max_bytes, dropped)
    tests[view] = ()
