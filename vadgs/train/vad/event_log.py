"""A VAD-GS event's log (:func:`~vadgs.train.vad.event.run_event`'s last step).

One entry per event in ``state["vad_events"]`` (:func:`log_event`), with one
:func:`attempt_log` per attempted instance, and a summary line (:func:`event_summary`) in
``state["pending_log"]`` for the loop to print.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

from vadgs.train.vad.config import VisibilityDensifyConfig
from vadgs.train.vad.reconstruct import InstanceReconstruction

__all__ = [
    "attempt_log",
    "event_summary",
    "instance_label",
    "log_event",
    "outcome_name",
    "repaired",
]


def attempt_log(
    instance: int, cls: str, references: list[int], recs: Sequence[InstanceReconstruction], work: float
) -> dict[str, Any]:
    """The log entry of an attempted ``instance`` of class ``cls``: each reference's reconstruction
    ``recs`` (:func:`~vadgs.train.vad.event.reconstruct_pairs`), ``work`` the pairs' planned work.

    ``instance``, ``class``, ``references``, ``views`` (each reference's group), ``points`` (the
    consistent MVS points of its groups, :attr:`InstanceReconstruction.consistent
    <vadgs.train.vad.reconstruct.InstanceReconstruction>`: before those the Gaussians already
    explain are left out and the rest thinned), ``added`` (the Gaussians added: what remains of
    ``points``), ``work`` (PatchMatch pixel-sweeps) and ``reason`` (each reference's
    ``InstanceReconstruction.reason``, joined).
    """  # noqa: D205
    return {
        "instance": instance,
        "class": cls,
        "references": references,
        "views": [rec.views for rec in recs],
        "points": sum(rec.consistent for rec in recs),
        "added": sum(int(rec.points.shape[0]) for rec in recs),
        "work": work,
        "reason": "; ".join(dict.fromkeys(rec.reason for rec in recs)),
    }


def repaired(log: Sequence[Mapping[str, Any]]) -> int:
    """The instances of an event's ``log`` that got new Gaussians (what ``max_instances`` counts)."""
    return sum(e["added"] > 0 for e in log)


def log_event(
    state: dict[str, Any], entry: dict[str, Any], config: VisibilityDensifyConfig, size: int
) -> None:
    """Append an event's log ``entry`` to ``state["vad_events"]`` and, with its
    :func:`event_summary`, to ``state["pending_log"]`` (at most ``size`` kept there: bounded when
    the loop does not pop it).
    """  # noqa: D205
    state["vad_events"].append(entry)
    summary = event_summary(entry, config)
    log_list = state.setdefault("pending_log", [])
    log_list.append({"kind": "visibility_densification", "summary": summary, **entry})
    del log_list[:-size]


def event_summary(entry: Mapping[str, Any], config: VisibilityDensifyConfig) -> str:
    """The one-line summary of an event's log ``entry`` (``summary`` in ``state["pending_log"]``).

    ``config``: the strategy's :class:`~vadgs.train.vad.config.VisibilityDensifyConfig` (its budgets).
    """
    added = [
        f"{instance_label(e['class'], e['instance'])} (+{e['added']})"
        for e in entry["instances"]
        if e["added"]
    ]
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
    model already explains the points; ``no_consistent_pixels``; ``lidar_disagrees``: the views' own
    LiDAR contradicts most of the checked matches; ``selection:...``).
    """
    failed = [e for e in instances if not e["added"]]
    if not failed:
        return ""
    why = "; ".join(
        f"{instance_label(e['class'], e['instance'])}: {e['reason'] or 'no new points'}" for e in failed[:4]
    )
    more = f"; {len(failed) - 4} more in the log" if len(failed) > 4 else ""
    return f"{len(failed)} added nothing ({why}{more}), "


def instance_label(cls: str, instance: int) -> str:
    """How the log names an instance: ``"sign 7"``, or ``"cell 10"`` for a derived one.

    A derived instance (class ``"static"``) is a cell of the ground grid standing in for a
    segmentation (a photo set's, a real log's).

    Example:
        >>> instance_label("sign", 7), instance_label("static", 10)
        ('sign 7', 'cell 10')
    """
    return f"cell {instance}" if cls == "static" else f"{cls} {instance}"


def outcome_name(reason: str) -> str:
    """An :class:`~vadgs.train.vad.reconstruct.InstanceReconstruction` reason without its detail.

    ``"selection:no_voxels: the reference sees none ..."`` → ``"selection:no_voxels"``; ``"ok"``,
    ``"ok (seen)"``, ``"explained"`` stay as they are.

    Example:
        >>> outcome_name("selection:no_voxels: the reference sees none (seen)")
        'selection:no_voxels (seen)'
    """
    head = reason.split(": ")[0]
    return head + " (seen)" if head != reason and reason.endswith("(seen)") else head
