"""A VAD-GS event, run by :class:`~vadgs.train.vad.VisibilityAwareDensification` (paper, Fig. 2).

:func:`run_event` is the event's one-way flow, given what it reads as an :class:`EventInputs`, in
named steps:

1. detection (:func:`~vadgs.train.vad.detect.detect`) and the candidates (:func:`candidates`: the
   flagged instances, each kept or left out by :func:`skip_reason`), ranked by
   :func:`~vadgs.train.vad.references.rank_instances`;
2. the budget (:func:`event_budget`; :func:`wave_room` and :func:`over_budget` as the instances
   are attempted);
3. the reconstruction, by waves of instances (:func:`reconstruct_instances`): each instance's
   references and plans (:func:`plan_instance`), every (instance, reference) pair of the wave
   matched together and finished in rank order (:func:`reconstruct_pairs`), one log entry per
   instance (:func:`~vadgs.train.vad.event_log.attempt_log`);
4. the new Gaussians (:func:`add_reconstructions`: each reconstruction's
   :func:`~vadgs.train.vad.gaussians.flat_gaussians` straight into the model's
   :func:`~vadgs.train.strategy.ops.add_gaussians`);
5. the log and its summary line (:mod:`vadgs.train.vad.event_log`).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Container, Mapping, MutableMapping, Sequence
from dataclasses import dataclass
from typing import Any, NamedTuple

import torch

from vadgs.checks import checking
from vadgs.train.strategy import ops
from vadgs.train.vad.config import VisibilityDensifyConfig
from vadgs.train.vad.detect import EventRenders, detect
from vadgs.train.vad.event_log import attempt_log, instance_label, log_event, outcome_name, repaired
from vadgs.train.vad.gaussians import flat_gaussians
from vadgs.train.vad.incomplete import IncompleteInstances
from vadgs.train.vad.inputs import VisibilityInputs
from vadgs.train.vad.matching import MatchPlan, match_plans
from vadgs.train.vad.priors import merge_priors
from vadgs.train.vad.reconstruct import InstanceReconstruction, ViewRender, finish_match, plan_matches
from vadgs.train.vad.reconstruct_config import ReconstructConfig
from vadgs.train.vad.references import pick_references, rank_instances
from vadgs.train.vad.survey import survey_instance
from vadgs.train.vad.visibility import VisibilityIndex

__all__ = [
    "Attempt",
    "Candidates",
    "EventBudget",
    "EventInputs",
    "Reconstructions",
    "add_reconstructions",
    "candidates",
    "event_budget",
    "over_budget",
    "plan_instance",
    "reconstruct_instances",
    "reconstruct_pairs",
    "run_event",
    "skip_reason",
    "wave_room",
]


@dataclass(frozen=True)
class EventInputs:
    """What one event (:func:`run_event`) reads: built by the strategy's ``densify`` for each event.

    Attributes:
        index: the scene's :class:`~vadgs.train.vad.visibility.VisibilityIndex`.
        inputs: the :class:`~vadgs.train.vad.inputs.VisibilityInputs` of the index.
        render: ``view -> ViewRender``, the loop's render of a view with the current Gaussians.
        generator: seeds the view-selection noise and point subsampling (or None).
        config: the strategy's :class:`~vadgs.train.vad.config.VisibilityDensifyConfig`.
        reconstruct: the :class:`~vadgs.train.vad.reconstruct_config.ReconstructConfig` the event
            uses (consecutive-frame selection when ``config.view_selection`` is off).
        track_nodes: track id → node index of ``params["node_ids"]``: the node a moving
            instance's new Gaussians join (:func:`add_reconstructions`).
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
    track_nodes: Mapping[int, int]
    trained_pixels: float | None
    on_progress: Callable[[str], None] | None = None
    on_addition: Callable[[dict[str, Any]], None] | None = None
    log_size: int = 64


# -- 1. the candidates -------------------------------------------------------------------------------


def skip_reason(
    instance: int,
    config: VisibilityDensifyConfig,
    classes: Mapping[int, str],
    moving: Container[int],
    has_nodes: bool,
    last_done: Mapping[int, int],
    event: int,
) -> str | None:
    """Why an event leaves a flagged ``instance`` out (the key it is counted under), or None.

    The rules, the first that holds: ``"skip_class"``, its class is one of
    ``config.skip_classes``; ``"static_model"``, it moves (one of ``moving``) and the model has no
    ``node_ids`` (a static model, e.g. gsplat's, cannot hold a moving object); ``"cooldown"``, it
    was reconstructed at most ``config.cooldown_events`` events ago (an instance never
    reconstructed never cools down).

    Args:
        instance: the flagged instance.
        config: its ``skip_classes`` and ``cooldown_events``.
        classes: instance → class name (:meth:`VisibilityIndex.classes
            <vadgs.train.vad.visibility.VisibilityIndex.classes>`; an instance absent has class ``""``).
        moving: the moving instances (the inputs' ``tracks``).
        has_nodes: whether the model has ``node_ids``.
        last_done: instance → the (0-based) event that last reconstructed it
            (``state["vad_last_done"]``).
        event: this event, 0-based.

    Example:
        >>> from vadgs.train.vad import VisibilityDensifyConfig
        >>> cfg = VisibilityDensifyConfig(cooldown_events=2, skip_classes=("sky",))
        >>> [skip_reason(i, cfg, {1: "sky"}, {2}, False, {3: 4}, 6) for i in (1, 2, 3, 4)]
        ['skip_class', 'static_model', 'cooldown', None]
    """
    if classes.get(instance, "") in config.skip_classes:
        return "skip_class"
    if instance in moving and not has_nodes:
        return "static_model"
    last = last_done.get(instance)  # None: never reconstructed, never cooling down
    if last is not None and event - last <= config.cooldown_events:
        return "cooldown"
    return None


class Candidates(NamedTuple):
    """The flagged instances of an event's detection, kept or left out (:func:`candidates`).

    Attributes:
        views: kept instance → its flagged views ``(view, pixels)``, in the detection's row order.
        skipped: how many flagged instances each reason of the ``skip`` rule left out.
        rows: the flagged (instance, view) rows.
        instances: the flagged instances, kept or left out.
    """

    views: dict[int, list[tuple[int, int]]]
    skipped: dict[str, int]
    rows: int
    instances: int

    def best_pixels(self) -> dict[int, int]:
        """Kept instance → its pixel count in the view where it has the most (what is ranked)."""
        return {i: max(c, key=lambda vp: vp[1])[1] for i, c in self.views.items()}


def candidates(
    rows: IncompleteInstances, views: Sequence[int], skip: Callable[[int], str | None]
) -> Candidates:
    """The flagged instances of ``rows``, those ``skip`` gives no reason for kept with their views.

    Args:
        rows: the detection's :class:`~vadgs.train.vad.incomplete.IncompleteInstances` (read in
            one transfer).
        views: the views tested, indexed by ``rows.view``.
        skip: instance → the reason it is left out, or None (:func:`skip_reason`).
    """
    # every row in one read, (instance, view, pixels) of the flagged ones kept in row order
    every = torch.stack([rows.instance, rows.view, rows.pixels, rows.flagged.long()], 1).tolist()
    table = [row[:3] for row in every if row[3]]
    flagged: dict[int, list[tuple[int, int]]] = {}
    for inst, view_k, px in table:
        if skip(inst) is None:
            flagged.setdefault(inst, []).append((views[view_k], px))
    flagged_ids = {row[0] for row in table}
    skipped: dict[str, int] = {}
    for inst in flagged_ids - set(flagged):
        why = skip(inst)  # not None: why it is not in flagged
        if why is not None:
            _count(skipped, why)
    return Candidates(flagged, skipped, len(table), len(flagged_ids))


# -- 2. the budget -----------------------------------------------------------------------------------


class EventBudget(NamedTuple):
    """An event's limits (:func:`event_budget`), ``math.inf`` where there is none.

    Attributes:
        work: PatchMatch pixel-sweeps (:func:`~vadgs.train.vad.matching.match_work`).
        seconds: wall-clock seconds since the event began.
    """

    work: float
    seconds: float


def event_budget(
    config: VisibilityDensifyConfig, trained_pixels: float | None, train_s: float
) -> EventBudget:
    """The budgets of an event: ``config.work_budget`` x ``trained_pixels`` PatchMatch pixel-sweeps,
    and the opt-in wall-clock cap ``config.time_budget`` x ``train_s`` (training seconds so far).

    Raises:
        ValueError: ``config.work_budget`` is set and ``trained_pixels`` is None.

    Example:
        >>> from vadgs.train.vad import VisibilityDensifyConfig
        >>> event_budget(VisibilityDensifyConfig(work_budget=2.0, time_budget=None), 1000.0, 60.0)
        EventBudget(work=2000.0, seconds=inf)
    """  # noqa: D205
    work = math.inf
    if config.work_budget is not None:
        if trained_pixels is None:
            raise ValueError(
                "EventInputs.trained_pixels: expected a number with config.work_budget set, got None"
            )
        work = config.work_budget * trained_pixels
    seconds = math.inf if config.time_budget is None else config.time_budget * train_s
    return EventBudget(work, seconds)


def wave_room(config: VisibilityDensifyConfig, repaired: int) -> float:
    """How many instances the next wave may attempt, ``repaired`` instances being repaired so far.

    ``config.max_instances`` counts the instances that add Gaussians (one that adds nothing uses
    up no slot), so a wave holds those that are attempted whatever the earlier ones add:
    ``max_instances - repaired`` (all without a cap), one with ``config.time_budget`` (the
    wall-clock cap is checked between instances). 0 or less: the event stops.
    """
    room = math.inf if config.max_instances is None else config.max_instances - repaired
    if config.time_budget is not None:
        room = min(room, 1)  # the wall-clock cap is checked between instances
    return room


def over_budget(budget: EventBudget, work: float, started: float) -> str | None:
    """``"work_budget"`` when ``work`` is past ``budget.work``, else ``"time_budget"`` when the clock
    (``time.perf_counter``) is past ``started`` + ``budget.seconds``, else None.

    Checked before each instance but an event's first (which is always attempted).
    """  # noqa: D205
    if work > budget.work:
        return "work_budget"
    if time.perf_counter() - started > budget.seconds:
        return "time_budget"
    return None


# -- 3. the reconstruction ---------------------------------------------------------------------------


class Attempt(NamedTuple):
    """An instance of a wave, planned (:func:`plan_instance`).

    Attributes:
        instance: the instance.
        references: its reference views (:func:`~vadgs.train.vad.references.pick_references`).
        plans: each reference's :class:`~vadgs.train.vad.matching.MatchPlan` or, when it has
            nothing to match, its :class:`~vadgs.train.vad.reconstruct.InstanceReconstruction`
            (the reason).
    """

    instance: int
    references: list[int]
    plans: list[MatchPlan | InstanceReconstruction]

    @property
    def work(self) -> float:
        """The PatchMatch pixel-sweeps of its plans."""
        return sum(p.work for p in self.plans)


def plan_instance(
    ev: EventInputs, instance: int, views: list[tuple[int, int]], renders: Callable[[int], ViewRender]
) -> Attempt:
    """An instance's references among its flagged ``views`` and each reference's plan.

    The instance surveyed in its flagged views (:func:`~vadgs.train.vad.survey.survey_instance`:
    one host read), :func:`~vadgs.train.vad.references.pick_references` (with
    ``config.whole_reference``, among the views where the instance is not cut by the image border
    when there are some), then :func:`~vadgs.train.vad.reconstruct.plan_matches` of its
    references (selection, crops).
    """
    cfg = ev.config
    seen = [v for v, _px in views]
    survey = survey_instance(ev.index, instance, seen, ev.reconstruct)
    whole = [v for v in seen if not survey.cut[v]] if cfg.whole_reference else None
    refs = pick_references(views, ev.inputs, cfg.references, cfg.min_frame_gap, whole)
    plans = plan_matches(ev.index, refs, instance, ev.reconstruct, ev.generator, renders, survey=survey)
    return Attempt(instance, refs, plans)


def reconstruct_pairs(
    ev: EventInputs,
    wave: Sequence[Attempt],
    renders: Callable[[int], ViewRender],
    occupied: dict[int | None, list[torch.Tensor]],
) -> list[list[InstanceReconstruction]]:
    """The reconstructions of a wave's (instance, reference) pairs, per instance and reference.

    Every plan matched together (:func:`~vadgs.train.vad.matching.match_plans`: few batched
    PatchMatch calls), then each finished in the wave's order
    (:func:`~vadgs.train.vad.reconstruct.finish_match`: consistency, fusion), away from the
    points of ``occupied`` in its frame (``None``: the world, else the moving instance's own),
    to which its new points are appended (the event's later pairs skip the cells it takes).
    """
    to_match = [p for a in wave for p in a.plans if isinstance(p, MatchPlan)]
    matched = iter(match_plans(ev.index, to_match, ev.reconstruct, renders))
    out = []
    for attempt in wave:
        frame = attempt.instance if attempt.instance in ev.inputs.tracks else None
        recs = []
        for plan in attempt.plans:
            if isinstance(plan, MatchPlan):
                taken = occupied.get(frame)
                rec = finish_match(
                    ev.index, plan, next(matched), ev.reconstruct, ev.generator, renders,
                    occupied=torch.cat(taken) if taken else None,
                )  # fmt: skip
            else:
                rec = plan  # nothing to match: its reason
            if rec.points.shape[0]:
                occupied.setdefault(frame, []).append(rec.points)
            recs.append(rec)
        out.append(recs)
    return out


class Reconstructions(NamedTuple):
    """What an event's waves made (:func:`reconstruct_instances`).

    Attributes:
        log: one :func:`~vadgs.train.vad.event_log.attempt_log` entry per attempted instance, in rank order.
        additions: ``(instance, reference, reconstruction)`` of each pair with new points, in
            rank order (its depth priors left out: merged already).
        outcomes: the pairs counted by how they ended (the reason without its detail).
        skipped: the instances left out by ``"work_budget"``, ``"time_budget"`` and
            ``"max_instances"``.
        work: the PatchMatch pixel-sweeps planned.
        seconds: the wall-clock seconds of the waves.
    """

    log: list[dict[str, Any]]
    additions: list[tuple[int, int, InstanceReconstruction]]
    outcomes: dict[str, int]
    skipped: dict[str, int]
    work: float
    seconds: float


def reconstruct_instances(
    ev: EventInputs,
    ranked: Sequence[int],
    views: Mapping[int, list[tuple[int, int]]],
    classes: Mapping[int, str],
    renders: Callable[[int], ViewRender],
    state: dict[str, Any],
    budget: EventBudget,
    started: float,
) -> Reconstructions:
    """The ``ranked`` instances reconstructed, by waves, within ``max_instances`` and the budget.

    A wave holds the next instances that are attempted whatever the earlier ones add
    (:func:`wave_room`), but for those :func:`over_budget` cuts (the work of the instances
    planned so far, the clock since ``started``; never the event's first): each planned
    (:func:`plan_instance`), then all its pairs reconstructed together
    (:func:`reconstruct_pairs`). So the instances attempted are those of one instance at a
    time.
    Per instance, in rank order: its depth priors merged into ``state["vad_priors"]`` (with
    ``config.geometric_losses``; only those beyond the voxels with ``config.mvs_prior_beyond_voxels``
    on a scene with LiDAR, :func:`~vadgs.train.vad.priors.merge_priors`) and
    ``state["vad_last_done"]`` set to this event.

    Args:
        ev: the event's inputs.
        ranked: the candidates, best first (:func:`~vadgs.train.vad.references.rank_instances`).
        views: candidate → its flagged views ``(view, pixels)`` (:attr:`Candidates.views`).
        classes: instance → class name (the progress line and the log).
        renders: the event's renders (of the model as the event began).
        state: the strategy's state.
        budget: the event's :class:`EventBudget`.
        started: the event's start (``time.perf_counter()``).
    """
    cfg = ev.config
    event = len(state["vad_events"])
    say = ev.on_progress or (lambda _line: None)
    log: list[dict[str, Any]] = []
    additions: list[tuple[int, int, InstanceReconstruction]] = []
    outcomes: dict[str, int] = {}
    skipped: dict[str, int] = {}
    occupied: dict[int | None, list[torch.Tensor]] = {}  # frame (None: world, else track) → points
    beyond = ev.index if cfg.mvs_prior_beyond_voxels and ev.inputs.lidar is not None else None  # LiDAR voxels
    work = seconds = 0.0
    pending = list(enumerate(ranked))
    while pending:
        room = wave_room(cfg, repaired(log))
        if room <= 0:
            _count(skipped, "max_instances", len(pending))
            break
        wave: list[Attempt] = []
        ta = time.perf_counter()
        while pending and len(wave) < room:
            k, inst = pending.pop(0)
            why = over_budget(budget, work, started) if log or wave else None
            if why is not None:
                _count(skipped, why)
                continue
            say(
                f"VAD-GS event {event + 1}: {len(ranked)} instances flagged, reconstructing "
                f"{k + 1}/{len(ranked)} ({instance_label(classes.get(inst, '?'), inst)}), "
                f"{time.perf_counter() - started:.0f} s"
            )
            wave.append(plan_instance(ev, inst, views[inst], renders))
            work += wave[-1].work
        for attempt, recs in zip(wave, reconstruct_pairs(ev, wave, renders, occupied)):
            for ref, rec in zip(attempt.references, recs):
                if rec.points.shape[0]:  # added when the event ends (add_reconstructions)
                    additions.append((attempt.instance, ref, rec._replace(depth=[], normal=[])))
                if cfg.geometric_losses:
                    merge_priors(state["vad_priors"], rec, beyond)
                _count(outcomes, outcome_name(rec.reason))
            state["vad_last_done"][attempt.instance] = event
            cls = classes.get(attempt.instance, "?")
            log.append(attempt_log(attempt.instance, cls, attempt.references, recs, attempt.work))
        seconds += time.perf_counter() - ta
    return Reconstructions(log, additions, outcomes, skipped, work, seconds)


# -- 4. the new Gaussians ----------------------------------------------------------------------------


def add_reconstructions(
    ev: EventInputs,
    params: MutableMapping[str, torch.Tensor],
    optimizers: Any,
    state: dict[str, Any],
    additions: Sequence[tuple[int, int, InstanceReconstruction]],
    renders: Callable[[int], ViewRender],
    event: int,
    step: int,
) -> None:
    """Add each reconstruction's :func:`~vadgs.train.vad.gaussians.flat_gaussians` to the model.

    In one hop, with their optimizer state and ``state``'s per-Gaussian rows
    (:func:`~vadgs.train.strategy.ops.add_gaussians`): static, or attached to the node
    ``ev.track_nodes`` gives the reconstruction's track; ``provenance`` (where the model has it)
    ``event`` (1-based). Done when the event's last instance is done, so that every render the
    event uses (kept from the loop or made during the event) is of the Gaussians as they were
    when it began. ``ev.on_addition`` (when set) gets each addition with its reference's render
    before it.

    Args:
        ev: the event's inputs (``config.new_opacity``, ``config.flatness``, ``track_nodes``,
            ``on_addition``).
        params: the per-Gaussian tensors, updated in place.
        optimizers: their moments follow (None: parameters only).
        state: the strategy state whose per-Gaussian rows follow.
        additions: ``(instance, reference, reconstruction)`` (:attr:`Reconstructions.additions`).
        renders: the event's renders (``on_addition``'s render before).
        event: the 1-based event number.
        step: the training step (``on_addition``'s).
    """
    cfg = ev.config
    for inst, ref, rec in additions:
        before = renders(ref) if ev.on_addition is not None else None
        node = -1 if rec.track is None else ev.track_nodes[rec.track]
        with checking(False):  # the reconstruction's tensors are the event's own: no value checks
            new = flat_gaussians(params, rec, None, cfg.new_opacity, cfg.flatness, event, node)
        ops.add_gaussians(params, optimizers, state, new)
        if ev.on_addition is not None and before is not None:
            ev.on_addition(
                {"instance": inst, "view": ref, "step": step, "added": int(rec.points.shape[0]),
                 "depth": before.depth[0], "alpha": before.alpha[0]}
            )  # fmt: skip


def run_event(
    ev: EventInputs,
    params: MutableMapping[str, torch.Tensor],
    optimizers: Any,
    state: dict[str, Any],
    step: int,
) -> dict[str, Any]:
    """One VAD-GS event (``VisibilityAwareDensification.densify``'s body); returns its log entry.

    The steps: :func:`detect` of the training views (reusing the loop's tests and renders kept in
    ``state``); the :func:`candidates` (flagged, no :func:`skip_reason`: class, static model,
    cooldown) ranked by :func:`rank_instances`; the :func:`event_budget`; the reconstruction of
    the instances by waves (:func:`reconstruct_instances`); the new Gaussians
    (:func:`add_reconstructions`) when the last instance is done; the log
    (:func:`~vadgs.train.vad.event_log.log_event`).

    The entry (appended to ``state["vad_events"]`` and, with its summary, to
    ``state["pending_log"]``): ``step``, ``cycle``, ``flagged`` / ``tested`` (rows of the
    detection), ``flagged_instances``, ``candidates``, ``attempted``, ``repaired`` (the attempted
    instances that got Gaussians), ``outcomes`` (the event's (instance, reference)
    reconstructions counted by reason without its detail: ``"ok"``, ``"ok (seen)"``,
    ``"explained"``, ``"selection:no_voxels"``, ...), ``skipped`` (the instances left out, by
    reason), ``instances`` (one :func:`~vadgs.train.vad.event_log.attempt_log` per attempted
    instance), ``added``, ``views_rendered``, ``tests_reused``, ``work`` / ``work_budget``
    (PatchMatch pixel-sweeps), ``budget_s`` and the seconds ``detect_s``, ``mvs_s``, ``total_s``.
    """
    cfg = ev.config
    renders = EventRenders(ev.render, state.get("vad_renders"))
    t0 = time.perf_counter()
    event = len(state["vad_events"])
    if ev.on_progress is not None:
        ev.on_progress(f"VAD-GS event {event + 1}: testing {len(ev.inputs.train_views)} views")
    tests = state.get("vad_tests") or {}
    rows, views = detect(ev.index, list(ev.inputs.train_views), renders, tests, cfg.incomplete)
    t1 = time.perf_counter()
    classes = ev.index.classes()  # incl. derived instances (scenes without maps)
    has_nodes = "node_ids" in getattr(params, "params", params)
    last_done = state["vad_last_done"]
    found = candidates(
        rows, views, lambda i: skip_reason(i, cfg, classes, ev.inputs.tracks, has_nodes, last_done, event)
    )
    best = found.best_pixels()
    ranked = rank_instances(best, classes, cfg.ranking)
    budget = event_budget(cfg, ev.trained_pixels, float(state.get("vad_train_s", 0.0)))
    made = reconstruct_instances(ev, ranked, found.views, classes, renders, state, budget, t0)
    add_reconstructions(ev, params, optimizers, state, made.additions, renders, event + 1, step)
    t2 = time.perf_counter()
    state["vad_tests"] = {}  # the next event tests (and renders) the views trained after this one
    state["vad_renders"] = {}
    entry = {
        "step": step,
        "cycle": state["vad_cycle"],
        "flagged": found.rows,
        "tested": int(rows.flagged.numel()),
        "flagged_instances": found.instances,
        "candidates": len(best),
        "attempted": len(made.log),
        "repaired": repaired(made.log),
        "outcomes": dict(sorted(made.outcomes.items())),
        "skipped": {**found.skipped, **made.skipped},
        "instances": made.log,
        "added": sum(e["added"] for e in made.log),
        "views_rendered": renders.rendered,
        "tests_reused": sum(v in tests for v in views),
        "work": made.work,
        "work_budget": None if math.isinf(budget.work) else budget.work,
        "budget_s": None if math.isinf(budget.seconds) else budget.seconds,
        "detect_s": t1 - t0,
        "mvs_s": made.seconds,
        "total_s": t2 - t0,
    }
    log_event(state, entry, cfg, ev.log_size)
    return entry


def _count(counts: dict[str, int], key: str, n: int = 1) -> None:
    """Add ``n`` to ``counts[key]`` (0 when absent)."""
    counts[key] = counts.get(key, 0) + n
