"""A VAD-GS event, run by :class:`~vadgs.train.vad.VisibilityAwareDensification`.

The event itself (:func:`run_event`: detection with :func:`detect`, ranking, references, the work
budget, reconstruction, :func:`add_reconstruction` and :func:`merge_priors`, the event's log), as
functions of the strategy's parts (its methods ``densify``, ``detect`` and ``_add`` delegate here),
and its pure steps: which flagged instances to reconstruct and from which views
(:func:`rank_instances`, :func:`pick_references`), the flat Gaussians made of an instance's fused
points (:func:`flat_gaussians`, oriented by :func:`normals_to_quats`), and the store of the loop's
renders reused by the event (kept in the strategy's state between events). The pure steps are
importable from :mod:`vadgs.train.vad`.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Collection, Mapping, MutableMapping
from typing import Any, NamedTuple

import torch

from vadgs.checks import check_finite, check_shape
from vadgs.geometry.rotation import rotation_to_quat
from vadgs.train.strategy import ops
from vadgs.train.vad.config import RANKINGS, VisibilityDensifyConfig
from vadgs.train.vad.incomplete import IncompleteConfig, IncompleteInstances, find_incomplete
from vadgs.train.vad.inputs import VisibilityInputs
from vadgs.train.vad.reconstruct import (
    InstanceReconstruction,
    ReconstructConfig,
    ViewRender,
    VisibilityIndex,
    reconstruct_instance,
)
from vadgs.train.vad.state import compact_render, expand_render

__all__ = [
    "EventInputs",
    "add_reconstruction",
    "detect",
    "detect_view",
    "flat_gaussians",
    "keep_render",
    "merge_priors",
    "normals_to_quats",
    "pick_references",
    "rank_instances",
    "run_event",
    "view_map",
]

_C0 = 0.28209479177387814


def pick_references(
    candidates: list[tuple[int, int]],
    scene: VisibilityInputs | Any,
    count: int,
    min_frame_gap: int = 3,
    whole: Collection[int] | None = None,
    tie: float = 0.05,
) -> list[int]:
    """Reference views of one instance: the largest first, then diverse ones.

    Views within ``tie`` of the largest pixel count are taken as equally large and ordered by
    view index: neighbouring frames often see an instance at a few percent of each other, and
    that difference follows the voxels' discretisation (another world frame, e.g. gsplat's
    normalised one, flips it), not the views.

    Args:
        candidates: ``(view, pixels)`` of the views where the instance was flagged.
        scene: :class:`~vadgs.train.vad.inputs.VisibilityInputs` or a vadgs :class:`~vadgs.data.Scene`
            (for each view's camera and frame).
        count: how many references at most.
        min_frame_gap: a further reference must come from a camera not chosen yet, or be at
            least this many frames from every chosen view of its camera.
        whole: the candidates in which the instance is whole (not cut by the image border). When
            given and no chosen view is one of them, the last reference is replaced by the
            largest of them that keeps the rule above (the close views with the most pixels may
            all cut off the same part, e.g. the top of a sign).
        tie: relative band below the largest count whose views count as equally large.

    Returns:
        View indices, largest first.

    Example:
        >>> from vadgs.data import load_scene, sample_scene_path
        >>> sc = load_scene(sample_scene_path())
        >>> [(sc.views[v].camera, sc.views[v].frame) for v in (0, 1, 3)]
        [('front', 16), ('front_left', 16), ('front', 17)]
        >>> pick_references([(0, 500), (3, 450), (1, 100)], sc, 2)  # view 3: same camera, 1 frame on
        [0, 1]
        >>> pick_references([(3, 500), (0, 490), (1, 100)], sc, 2)  # 0 and 3 tie (2 %): the first view
        [0, 1]
    """
    if isinstance(scene, VisibilityInputs):
        cam, frame = scene.view_cameras, scene.view_frames
    else:
        cam, frame = [v.camera for v in scene.views], [v.frame for v in scene.views]

    def apart(view: int, chosen: list[int]) -> bool:
        return all(cam[c] != cam[view] or abs(frame[c] - frame[view]) >= min_frame_gap for c in chosen)

    top = max((px for _v, px in candidates), default=0)
    tied = {v for v, px in candidates if px >= (1 - tie) * top}

    def rank(vp: tuple[int, int]) -> tuple[int, ...]:  # the tied views first, by index; then by size
        return (0, vp[0]) if vp[0] in tied else (1, -vp[1], vp[0])

    order = [v for v, _px in sorted(candidates, key=rank)]
    chosen: list[int] = []
    for view in order:
        if len(chosen) >= count:
            break
        if apart(view, chosen):
            chosen.append(view)
    if whole is not None and count >= 2 and chosen and not set(chosen) & set(whole):
        keep = chosen[: count - 1]
        extra = next((v for v in order if v in whole and v not in keep and apart(v, keep)), None)
        if extra is not None:
            chosen = [*keep, extra]
    return chosen


def rank_instances(
    pixels: dict[int, int], classes: dict[int, str], ranking: str = "class_round_robin"
) -> list[int]:
    """Order flagged instances for reconstruction.

    Args:
        pixels: instance id → its size (pixels in its best flagged view).
        classes: instance id → class name (missing ids form one class ``""``).
        ranking: ``"pixels"`` (largest first) or ``"class_round_robin"`` (the largest of each class
            in turn; classes ordered by their largest instance).

    Example:
        >>> px = {1: 900, 2: 800, 3: 700, 7: 50, 9: 300}
        >>> cls = {1: "building", 2: "building", 3: "building", 7: "sign", 9: "tree"}
        >>> rank_instances(px, cls, "pixels")
        [1, 2, 3, 9, 7]
        >>> rank_instances(px, cls)
        [1, 9, 7, 2, 3]
    """
    if ranking not in RANKINGS:
        raise ValueError(f"ranking: expected one of {RANKINGS}, got {ranking!r}")
    order = sorted(pixels, key=lambda i: (-pixels[i], i))
    if ranking == "pixels":
        return order
    queues: dict[str, list[int]] = {}
    for i in order:  # classes in the order of their largest instance
        queues.setdefault(classes.get(i, ""), []).append(i)
    out: list[int] = []
    while any(queues.values()):
        for q in queues.values():
            if q:
                out.append(q.pop(0))
    return out


def normals_to_quats(normals: torch.Tensor) -> torch.Tensor:
    """``wxyz`` quaternions of rotations whose third axis is the given unit normal ``(N, 3)``.

    A Gaussian with scales ``(s, s, t)``, ``t << s``, and this rotation is a disc in the plane of
    the normal. On the device and in the dtype of ``normals``.

    Example:
        >>> from vadgs.geometry import quaternion_to_rotation
        >>> n = torch.tensor([[0.0, 0.0, 1.0], [0.6, 0.8, 0.0]])
        >>> torch.allclose(quaternion_to_rotation(normals_to_quats(n))[:, :, 2], n, atol=1e-6)
        True
    """
    check_shape(normals, "normals", ("N", 3))
    check_finite(normals, "normals")
    n = torch.nn.functional.normalize(normals, dim=-1)
    helper = torch.where(
        n[:, 2:3].abs() < 0.9,
        n.new_tensor([0.0, 0.0, 1.0]).expand_as(n),
        n.new_tensor([1.0, 0.0, 0.0]).expand_as(n),
    )
    a = torch.nn.functional.normalize(torch.cross(helper, n, dim=-1), dim=-1)
    b = torch.cross(n, a, dim=-1)
    R = torch.stack([a, b, n], dim=-1)  # columns: the Gaussian's axes in the world
    return rotation_to_quat(R)


def flat_gaussians(
    params: Mapping[str, torch.Tensor] | Any,
    rec: InstanceReconstruction,
    keep: torch.Tensor | None = None,
    new_opacity: float = 0.5,
    flatness: float = 0.2,
    event: int = 1,
) -> dict[str, torch.Tensor]:
    """New flat Gaussians from an instance's (kept) fused points, in ``params``' layout.

    Each point becomes a disc oriented by its MVS normal (:func:`normals_to_quats`), of width its
    spacing and thickness ``flatness`` times that, with opacity ``new_opacity`` and the MVS colour,
    on the device and in the dtype of ``params``' means. Where ``params`` has a ``provenance``
    entry the new rows get ``event`` (1-based). Entries of other layouts: gsplat's appearance
    ``colors`` ``(N, 3)`` get the logit of the MVS colour (as gsplat's ``simple_trainer``
    initialises them); every other unknown per-Gaussian entry (e.g. gsplat's ``features``) gets
    zeros of its trailing shape and dtype. ``node_ids`` is left to the caller (it depends on the
    model's tracks). Not differentiable (new leaf values).

    Args:
        params: the per-Gaussian tensors (vadgs's or gsplat's names,
            :func:`~vadgs.train.strategy.ops.param_names`).
        rec: the instance's :class:`~vadgs.train.vad.reconstruct.InstanceReconstruction`.
        keep: boolean mask ``(M,)`` of the points to use (default all).
        new_opacity: opacity of the new Gaussians, in (0, 1).
        flatness: thickness along the normal relative to the width.
        event: the 1-based event number written to ``provenance``.

    Returns:
        ``{name: (m, ...)}`` for every entry of ``params`` but ``node_ids``.
    """
    names = ops.param_names(params)
    p = getattr(params, "params", params)
    ref = p[names.means]
    dev, dt = ref.device, ref.dtype
    if keep is None:
        keep = torch.ones(rec.points.shape[0], dtype=torch.bool, device=rec.points.device)
    keep = keep.to(rec.points.device)
    pts, nrm, col, spc = (x[keep].to(dev, dt) for x in (rec.points, rec.normals, rec.colors, rec.spacing))
    m = pts.shape[0]
    width = spc.clamp(min=1e-4)
    opacity = torch.full((m,), new_opacity, device=dev, dtype=dt)
    new = {
        names.means: pts,
        names.quats: normals_to_quats(nrm),
        names.log_scales: torch.log(torch.stack([width, width, width * flatness], -1)),
        names.opacity_logits: torch.log(opacity / (1 - opacity)),
    }
    if names.sh_dc is not None:
        new[names.sh_dc] = ((col[:, :3] - 0.5) / _C0)[:, None, :]
        new[names.sh_rest] = torch.zeros(m, *p[names.sh_rest].shape[1:], device=dev, dtype=dt)
    if "provenance" in p:
        new["provenance"] = torch.full((m,), event, dtype=torch.int64, device=p["provenance"].device)
    for k in p.keys():
        if k in new or k == "node_ids":
            continue
        t = p[k]
        if k == "colors" and t.shape[1:] == (3,) and t.is_floating_point():
            new[k] = torch.logit(col[:, :3].clamp(1e-4, 1 - 1e-4)).to(t)
        else:
            new[k] = torch.zeros(m, *t.shape[1:], device=t.device, dtype=t.dtype)
    return new


def _event_summary(entry: Mapping[str, Any], config: Any) -> str:
    """The one-line summary of an event's log ``entry`` (``summary`` in ``state["pending_log"]``).

    ``config``: the strategy's :class:`~vadgs.train.vad.config.VisibilityDensifyConfig` (its budgets).
    """
    added = [f"{e['class']} {e['instance']} (+{e['added']})" for e in entry["instances"] if e["added"]]
    cut = ", ".join(f"{n} {why}" for why, n in entry["skipped"].items()) or "none"
    summary = (
        f"visibility-aware densification: {entry['flagged_instances']} instances flagged, "
        f"{entry['attempted']} attempted, {entry['repaired']} repaired (+{entry['added']} Gaussians), "
        f"{_failed(entry['instances'])}skipped: {cut}; {entry['total_s']:.1f} s; "
        f"added to {', '.join(added) or 'none'}"
    )
    if "work_budget" in entry["skipped"]:
        summary += (
            f" (work budget {entry['work_budget']:.3g} PatchMatch pixel-sweeps = {config.work_budget:g}"
            " x training pixels so far; the instances left are tried at the next event)"
        )
    if "time_budget" in entry["skipped"]:
        summary += (
            f" (wall-clock cap {entry['budget_s']:.1f} s = {config.time_budget:g} x training time so far"
            " reached: this run now depends on the machine's speed and load)"
        )
    return summary


def _failed(instances: list[Mapping[str, Any]]) -> str:
    """``"N added nothing (class id: reason; ...), "`` of the attempted instances, or ``""`` when all added.

    The reasons are :class:`~vadgs.train.vad.reconstruct.InstanceReconstruction`'s (``explained``: the
    model already explains the points; ``no_consistent_pixels``; ``selection:...``).
    """
    failed = [e for e in instances if not e["added"]]
    if not failed:
        return ""
    why = "; ".join(f"{e['class']} {e['instance']}: {e['reason'] or 'no new points'}" for e in failed[:4])
    more = f"; {len(failed) - 4} more in the log" if len(failed) > 4 else ""
    return f"{len(failed)} added nothing ({why}{more}), "


class EventRenders:
    """Renders of one event: the loop's own renders kept in the state, else rendered once."""

    def __init__(self, render: Callable[[int], ViewRender], kept: Mapping[int, tuple] | None = None) -> None:
        self.render, self.kept, self.cache = render, kept or {}, {}
        self.rendered = 0

    def __call__(self, view: int) -> ViewRender:
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

    A view in ``tests`` (the fields of its one-view test, from the loop's render) is not rendered
    again; the others are rendered with ``render``. Returns ``(rows, views)``, ``rows.view``
    indexing ``views``, on the device of the first view's test.
    """
    parts = []
    for k, v in enumerate(views):
        if v in tests:
            fields = tests[v]
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


def merge_priors(priors: dict[int, tuple[torch.Tensor, torch.Tensor]], rec: InstanceReconstruction) -> None:
    """Keep the MVS depth and normals of ``rec``'s views in ``priors`` (``state["vad_priors"]``).

    Where a view already has priors, the new ones replace them only where the new depth exists.
    """
    for v, d, n in zip(rec.views, rec.depth, rec.normal):
        old = priors.get(v)
        if old is not None:
            has = d > 0
            d = torch.where(has, d, old[0])
            n = torch.where(has, n, old[1])
        priors[v] = (d, n)


def add_reconstruction(
    params: MutableMapping[str, torch.Tensor],
    optimizers: Any,
    state: dict[str, Any] | None,
    rec: InstanceReconstruction,
    keep: torch.Tensor | None,
    event: int,
    config: VisibilityDensifyConfig,
    track_nodes: Callable[[], Mapping[int, int]],
) -> None:
    """Add the :func:`flat_gaussians` of ``rec``'s (kept) points (``VisibilityAwareDensification._add``).

    Through :func:`~vadgs.train.strategy.ops.add_gaussians`, with ``node_ids`` (when ``params`` has
    them) the node of the instance's track (``track_nodes()``: track id → node, asked only then),
    or -1 for a static instance.
    """
    new = flat_gaussians(params, rec, keep, config.new_opacity, config.flatness, event)
    p = getattr(params, "params", params)
    node_ids = None
    if "node_ids" in p:
        node = -1 if rec.track is None else track_nodes()[rec.track]
        m = new[ops.param_names(params).means].shape[0]
        node_ids = torch.full((m,), node, dtype=torch.int64, device=p["node_ids"].device)
    ops.add_gaussians(params, optimizers, state, new, node_ids)


class EventInputs(NamedTuple):
    """What one event (:func:`run_event`) reads: built by the strategy's ``densify`` for each event.

    Attributes:
        index: the scene's :class:`~vadgs.train.vad.visibility.VisibilityIndex`.
        inputs: the :class:`~vadgs.train.vad.inputs.VisibilityInputs` of the index.
        render: ``view -> ViewRender``, the loop's render of a view with the current Gaussians.
        generator: seeds the view-selection noise and point subsampling (or None).
        config: the strategy's :class:`~vadgs.train.vad.config.VisibilityDensifyConfig`.
        reconstruct: the :class:`~vadgs.train.vad.reconstruct_config.ReconstructConfig` the event
            uses (consecutive-frame selection when ``config.view_selection`` is off).
        add: ``add(params, optimizers, state, rec, event=...)``: adds the flat Gaussians of an
            :class:`~vadgs.train.vad.reconstruct.InstanceReconstruction` (e.g. with
            :func:`add_reconstruction`).
        trained_pixels: training pixels so far, the scale of ``config.work_budget`` (None when
            that is None).
        on_progress: optional callback given one line while the event runs.
        on_addition: optional callback given ``{"instance", "view", "step", "added", "depth",
            "alpha"}`` each time an instance gets new Gaussians.
        log_size: at most this many events kept in ``state["pending_log"]``.
    """

    index: VisibilityIndex
    inputs: VisibilityInputs
    render: Callable[[int], ViewRender]
    generator: torch.Generator | None
    config: VisibilityDensifyConfig
    reconstruct: ReconstructConfig
    add: Callable[..., None]
    trained_pixels: float | None
    on_progress: Callable[[str], None] | None = None
    on_addition: Callable[[dict[str, Any]], None] | None = None
    log_size: int = 64


def run_event(
    ev: EventInputs,
    params: MutableMapping[str, torch.Tensor],
    optimizers: Any,
    state: dict[str, Any],
    step: int,
) -> dict[str, Any]:
    """One VAD-GS event (``VisibilityAwareDensification.densify``'s body); returns its log.

    Detection (:func:`detect` of the training views, reusing the loop's tests and renders kept in
    ``state``), the candidates (flagged, not skipped by class, model or cooldown) ranked by
    :func:`rank_instances`, then per instance, within ``max_instances`` and the budgets (PatchMatch
    work against ``work_budget`` x ``ev.trained_pixels``; the opt-in wall-clock ``time_budget``):
    :func:`pick_references`, :func:`~vadgs.train.vad.reconstruct.reconstruct_instance` per
    reference, ``ev.add`` of the new points, :func:`merge_priors`. The log entry is appended
    to ``state["vad_events"]`` and, with its summary, to ``state["pending_log"]`` (at most
    ``ev.log_size`` kept).

    The entry's ``instances`` has one dict per attempted instance: ``instance``, ``class``,
    ``references`` (its reference views), ``views`` (each reference's group), ``points`` (the
    consistent MVS points of its groups, :attr:`InstanceReconstruction.consistent
    <vadgs.train.vad.reconstruct.InstanceReconstruction>`: before those the Gaussians already
    explain are left out and the rest thinned), ``added`` (the Gaussians added: what remains of
    ``points``), ``work`` (PatchMatch pixel-sweeps) and ``reason`` (each reference's
    ``InstanceReconstruction.reason``, joined).
    """
    cfg = ev.config
    inputs = ev.inputs
    index = ev.index
    renders = EventRenders(ev.render, state.get("vad_renders"))
    t0 = time.perf_counter()
    event = len(state["vad_events"])
    say = ev.on_progress or (lambda _line: None)
    say(f"VAD-GS event {event + 1}: testing {len(inputs.train_views)} views")
    tests = state.get("vad_tests") or {}
    rows, views = detect(index, list(inputs.train_views), renders, tests, cfg.incomplete)
    t1 = time.perf_counter()
    classes = index.classes()  # incl. derived instances (scenes without maps)
    has_nodes = "node_ids" in getattr(params, "params", params)

    def skip_reason(inst: int) -> str | None:
        if classes.get(inst, "") in cfg.skip_classes:
            return "skip_class"
        if inst in inputs.tracks and not has_nodes:
            return "static_model"  # a static model (no node_ids) cannot hold a moving object
        last = state["vad_last_done"].get(inst)  # None: never reconstructed, never cooling down
        if last is not None and event - last <= cfg.cooldown_events:
            return "cooldown"
        return None

    # the flagged views of each candidate instance, with its pixel count there
    flagged: dict[int, list[tuple[int, int]]] = {}
    skipped: dict[str, int] = {}
    for k in torch.nonzero(rows.flagged).squeeze(1).tolist():
        inst = int(rows.instance[k])
        if skip_reason(inst) is None:
            flagged.setdefault(inst, []).append((views[int(rows.view[k])], int(rows.pixels[k])))
    flagged_ids = set(rows.instance[rows.flagged].tolist())
    for inst in flagged_ids - set(flagged):
        why = skip_reason(inst)
        skipped[why] = skipped.get(why, 0) + 1
    best = {i: max(c, key=lambda vp: vp[1])[1] for i, c in flagged.items()}
    ranked = rank_instances(best, classes, cfg.ranking)
    added, log = 0, []
    t_mvs = 0.0
    work_budget = math.inf
    if cfg.work_budget is not None:
        if ev.trained_pixels is None:
            raise ValueError(
                "EventInputs.trained_pixels: expected a number with config.work_budget set, got None"
            )
        work_budget = cfg.work_budget * ev.trained_pixels
    time_cap = math.inf
    if cfg.time_budget is not None:
        time_cap = cfg.time_budget * float(state.get("vad_train_s", 0.0))
    work = 0.0  # PatchMatch pixel-sweeps of this event so far (match_work)
    occupied: dict[int | None, list[torch.Tensor]] = {}  # frame (None: world, else track) → points
    done = repaired = 0
    for k, inst in enumerate(ranked):
        if cfg.max_instances is not None and done >= cfg.max_instances:
            skipped["max_instances"] = skipped.get("max_instances", 0) + 1
            continue
        if log and work > work_budget:
            skipped["work_budget"] = skipped.get("work_budget", 0) + 1
            continue
        if log and time.perf_counter() - t0 > time_cap:
            skipped["time_budget"] = skipped.get("time_budget", 0) + 1
            continue
        say(
            f"VAD-GS event {event + 1}: {len(ranked)} instances flagged, reconstructing "
            f"{k + 1}/{len(ranked)} ({classes.get(inst, '?')} {inst}), {time.perf_counter() - t0:.0f} s"
        )
        whole = (
            [v for v, _px in flagged[inst] if not index.cut_by_border(v, inst)]
            if cfg.whole_reference
            else None
        )
        refs = pick_references(flagged[inst], inputs, cfg.references, cfg.min_frame_gap, whole)
        entry_views, points, n_new_total, reasons, work0 = [], 0, 0, [], work
        frame_key = inst if inst in inputs.tracks else None
        for ref in refs:
            ta = time.perf_counter()
            taken = occupied.get(frame_key)
            rec = reconstruct_instance(
                index, ref, inst, ev.reconstruct, ev.generator, renders,
                occupied=torch.cat(taken) if taken else None,
            )  # fmt: skip
            t_mvs += time.perf_counter() - ta
            work += rec.work
            n_new = int(rec.points.shape[0])
            if n_new:
                ev.add(params, optimizers, state, rec, event=event + 1)
                occupied.setdefault(frame_key, []).append(rec.points)
                if ev.on_addition is not None:
                    before = renders(ref)
                    ev.on_addition(
                        {"instance": inst, "view": ref, "step": step, "added": n_new,
                         "depth": before.depth[0], "alpha": before.alpha[0]}
                    )  # fmt: skip
            if cfg.geometric_losses:
                merge_priors(state["vad_priors"], rec)
            entry_views.append(rec.views)
            points += rec.consistent
            n_new_total += n_new
            reasons.append(rec.reason)
        added += n_new_total
        done += n_new_total > 0  # an instance that added nothing does not use up a max_instances slot
        repaired += n_new_total > 0
        state["vad_last_done"][inst] = event
        log.append(
            {
                "instance": inst,
                "class": classes.get(inst, "?"),
                "references": refs,
                "views": entry_views,
                "points": points,
                "added": n_new_total,
                "work": work - work0,
                "reason": "; ".join(dict.fromkeys(reasons)),
            }
        )
    t2 = time.perf_counter()
    state["vad_tests"] = {}  # the next event tests (and renders) the views trained after this one
    state["vad_renders"] = {}
    entry = {
        "step": step,
        "cycle": state["vad_cycle"],
        "flagged": int(rows.flagged.sum()),
        "tested": int(rows.flagged.numel()),
        "flagged_instances": len(flagged_ids),
        "candidates": len(best),
        "attempted": len(log),
        "repaired": repaired,
        "skipped": skipped,
        "instances": log,
        "added": added,
        "views_rendered": renders.rendered,
        "tests_reused": sum(v in tests for v in views),
        "work": work,
        "work_budget": None if math.isinf(work_budget) else work_budget,
        "budget_s": None if math.isinf(time_cap) else time_cap,
        "detect_s": t1 - t0,
        "mvs_s": t_mvs,
        "total_s": t2 - t0,
    }
    state["vad_events"].append(entry)
    summary = _event_summary(entry, cfg)
    log_list = state.setdefault("pending_log", [])
    log_list.append({"kind": "visibility_densification", "summary": summary, **entry})
    del log_list[: -ev.log_size]  # bounded when the loop does not pop it
    return entry
