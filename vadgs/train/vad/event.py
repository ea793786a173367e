"""A VAD-GS event, run by :class:`~vadgs.train.vad.VisibilityAwareDensification` (paper, Fig. 2).

:func:`run_event` is the event's one-way flow, given what it reads as an :class:`EventInputs`:
detection (:mod:`vadgs.train.vad.detect`), ranking and references
(:mod:`vadgs.train.vad.references`), the work budget, reconstruction
(:mod:`vadgs.train.vad.reconstruct`), new Gaussians (:mod:`vadgs.train.vad.gaussians`) and priors
(:mod:`vadgs.train.vad.priors`), and the event's log and summary line.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Mapping, MutableMapping
from dataclasses import dataclass
from typing import Any

import torch

from vadgs.train.vad.config import VisibilityDensifyConfig
from vadgs.train.vad.detect import EventRenders, detect
from vadgs.train.vad.inputs import VisibilityInputs
from vadgs.train.vad.priors import merge_priors
from vadgs.train.vad.reconstruct import (
    InstanceReconstruction,
    MatchPlan,
    ViewRender,
    finish_match,
    match_plans,
    plan_match,
)
from vadgs.train.vad.reconstruct_config import ReconstructConfig
from vadgs.train.vad.references import pick_references, rank_instances
from vadgs.train.vad.visibility import VisibilityIndex

__all__ = [
    "EventInputs",
    "run_event",
]


def _event_summary(entry: Mapping[str, Any], config: Any) -> str:
    """The one-line summary of an event's log ``entry`` (``summary`` in ``state["pending_log"]``).

    ``config``: the strategy's :class:`~vadgs.train.vad.config.VisibilityDensifyConfig` (its budgets).
    """
    added = [f"{_label(e['class'], e['instance'])} (+{e['added']})" for e in entry["instances"] if e["added"]]
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
    why = "; ".join(
        f"{_label(e['class'], e['instance'])}: {e['reason'] or 'no new points'}" for e in failed[:4]
    )
    more = f"; {len(failed) - 4} more in the log" if len(failed) > 4 else ""
    return f"{len(failed)} added nothing ({why}{more}), "


def _label(cls: str, instance: int) -> str:
    """How the log names an instance: ``"sign 7"``, or ``"cell 10"`` for a derived one.

    A derived instance (class ``"static"``) is a cell of the ground grid standing in for a
    segmentation (a photo set's, a real log's).
    """
    return f"cell {instance}" if cls == "static" else f"{cls} {instance}"


def _outcome(reason: str) -> str:
    """An :class:`~vadgs.train.vad.reconstruct.InstanceReconstruction` reason without its detail.

    ``"selection:no_voxels: the reference sees none ..."`` → ``"selection:no_voxels"``; ``"ok"``,
    ``"ok (seen)"``, ``"explained"`` stay as they are.
    """
    head = reason.split(": ")[0]
    return head + " (seen)" if head != reason and reason.endswith("(seen)") else head


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
    :func:`pick_references`, and :func:`~vadgs.train.vad.reconstruct.reconstruct_instance` of each
    reference in three parts: every (instance, reference) pair of a *wave* of instances planned
    (:func:`~vadgs.train.vad.reconstruct.plan_match`: selection, crops), all matched together
    (:func:`~vadgs.train.vad.reconstruct.match_plans`: few batched PatchMatch calls, as few
    kernel launches as the crops' sizes allow), then each finished in rank order
    (:func:`~vadgs.train.vad.reconstruct.finish_match`: consistency, fusion), and
    :func:`merge_priors`. A wave holds the instances that are attempted whatever the earlier ones
    add (``max_instances`` counts those that add: ``max_instances`` minus those done; all without
    a cap; one with ``time_budget``, checked between instances), so the instances attempted are
    those of one instance at a time; the work budget is checked as each is planned (the work is
    a function of the crops). ``ev.add`` of the new points when the last instance is done, so
    that every render the event uses (kept from the loop or made during the event) is of the
    Gaussians as they were when it began, whatever the order in which views are first asked for
    (later instances skip the cells earlier ones took instead). The log entry is appended
    to ``state["vad_events"]`` and, with its summary, to ``state["pending_log"]`` (at most
    ``ev.log_size`` kept).

    The entry's ``instances`` has one dict per attempted instance: ``instance``, ``class``,
    ``references`` (its reference views), ``views`` (each reference's group), ``points`` (the
    consistent MVS points of its groups, :attr:`InstanceReconstruction.consistent
    <vadgs.train.vad.reconstruct.InstanceReconstruction>`: before those the Gaussians already
    explain are left out and the rest thinned), ``added`` (the Gaussians added: what remains of
    ``points``), ``work`` (PatchMatch pixel-sweeps) and ``reason`` (each reference's
    ``InstanceReconstruction.reason``, joined); the entry's ``outcomes`` counts the event's
    (instance, reference) reconstructions by reason (without its detail: ``"ok"``, ``"ok (seen)"``,
    ``"explained"``, ``"selection:no_voxels"``, ...).
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
    # every row in one read, (instance, view, pixels) of the flagged ones kept in row order
    every = torch.stack([rows.instance, rows.view, rows.pixels, rows.flagged.long()], 1).tolist()
    table = [row[:3] for row in every if row[3]]
    for inst, view_k, px in table:
        if skip_reason(inst) is None:
            flagged.setdefault(inst, []).append((views[view_k], px))
    flagged_ids = {row[0] for row in table}
    for inst in flagged_ids - set(flagged):
        why = skip_reason(inst)  # not None: why it is not in flagged
        if why is not None:
            skipped[why] = skipped.get(why, 0) + 1
    best = {i: max(c, key=lambda vp: vp[1])[1] for i, c in flagged.items()}
    ranked = rank_instances(best, classes, cfg.ranking)
    added = 0
    log: list[dict[str, Any]] = []
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
    additions: list[tuple[int, int, Any]] = []  # (instance, reference, reconstruction), added at the end
    outcomes: dict[str, int] = {}  # how each (instance, reference) reconstruction ended (_outcome)
    done = repaired = 0
    pending = list(enumerate(ranked))
    while pending:
        # A wave: the instances that can be attempted whatever the others add (max_instances counts
        # those that add), each pair planned (selected and cropped), then all matched together.
        room = math.inf if cfg.max_instances is None else cfg.max_instances - done
        if cfg.time_budget is not None:
            room = min(room, 1)  # the wall-clock cap is checked between instances
        if room <= 0:
            skipped["max_instances"] = skipped.get("max_instances", 0) + len(pending)
            break
        # (instance, its references, each reference's plan or, when nothing to match, result)
        wave: list[tuple[int, list[int], list[MatchPlan | InstanceReconstruction]]] = []
        ta = time.perf_counter()
        while pending and len(wave) < room:
            k, inst = pending.pop(0)
            if (log or wave) and work > work_budget:
                skipped["work_budget"] = skipped.get("work_budget", 0) + 1
                continue
            if (log or wave) and time.perf_counter() - t0 > time_cap:
                skipped["time_budget"] = skipped.get("time_budget", 0) + 1
                continue
            say(
                f"VAD-GS event {event + 1}: {len(ranked)} instances flagged, reconstructing "
                f"{k + 1}/{len(ranked)} ({_label(classes.get(inst, '?'), inst)}), "
                f"{time.perf_counter() - t0:.0f} s"
            )
            whole = None
            if cfg.whole_reference:
                seen = [v for v, _px in flagged[inst]]
                whole = [v for v, cut in zip(seen, index.cut_by_border_views(seen, inst)) if not cut]
            refs = pick_references(flagged[inst], inputs, cfg.references, cfg.min_frame_gap, whole)
            plans = [plan_match(index, ref, inst, ev.reconstruct, ev.generator, renders) for ref in refs]
            wave.append((inst, refs, plans))
            work += sum(p.work for p in plans)
        to_match = [p for _, _, plans in wave for p in plans if isinstance(p, MatchPlan)]
        matched = iter(match_plans(index, to_match, ev.reconstruct, renders))
        for inst, refs, plans in wave:
            entry_views, points, n_new_total, reasons = [], 0, 0, []
            frame_key = inst if inst in inputs.tracks else None
            for ref, plan in zip(refs, plans):
                if isinstance(plan, MatchPlan):
                    taken = occupied.get(frame_key)
                    rec = finish_match(
                        index, plan, next(matched), ev.reconstruct, ev.generator, renders,
                        occupied=torch.cat(taken) if taken else None,
                    )  # fmt: skip
                else:
                    rec = plan  # nothing to match: its reason
                n_new = int(rec.points.shape[0])
                if n_new:  # added when the event ends: every render of the event is of the model before it
                    additions.append((inst, ref, rec._replace(depth=[], normal=[])))  # priors merged below
                    occupied.setdefault(frame_key, []).append(rec.points)
                if cfg.geometric_losses:
                    merge_priors(state["vad_priors"], rec)
                entry_views.append(rec.views)
                points += rec.consistent
                n_new_total += n_new
                reasons.append(rec.reason)
                outcome = _outcome(rec.reason)
                outcomes[outcome] = outcomes.get(outcome, 0) + 1
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
                    "work": sum(p.work for p in plans),
                    "reason": "; ".join(dict.fromkeys(reasons)),
                }
            )
        t_mvs += time.perf_counter() - ta
    for inst, ref, rec in additions:
        before = renders(ref) if ev.on_addition is not None else None
        ev.add(params, optimizers, state, rec, event=event + 1)
        if ev.on_addition is not None and before is not None:
            ev.on_addition(
                {"instance": inst, "view": ref, "step": step, "added": int(rec.points.shape[0]),
                 "depth": before.depth[0], "alpha": before.alpha[0]}
            )  # fmt: skip
    t2 = time.perf_counter()
    state["vad_tests"] = {}  # the next event tests (and renders) the views trained after this one
    state["vad_renders"] = {}
    entry = {
        "step": step,
        "cycle": state["vad_cycle"],
        "flagged": len(table),
        "tested": int(rows.flagged.numel()),
        "flagged_instances": len(flagged_ids),
        "candidates": len(best),
        "attempted": len(log),
        "repaired": repaired,
        "outcomes": dict(sorted(outcomes.items())),
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
