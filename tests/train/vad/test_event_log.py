"""A VAD-GS event's log (:mod:`vadgs.train.vad.event_log`) against hand-computed entries and lines."""

from __future__ import annotations

import torch

from vadgs.train.vad.config import VisibilityDensifyConfig
from vadgs.train.vad.event_log import (
    attempt_log,
    event_summary,
    instance_label,
    log_event,
    outcome_name,
    repaired,
)
from vadgs.train.vad.reconstruct import InstanceReconstruction


def _rec(points: int, consistent: int, views: list[int], reason: str) -> InstanceReconstruction:
    return InstanceReconstruction(
        points=torch.zeros(points, 3),
        normals=torch.zeros(points, 3),
        colors=torch.zeros(points, 3),
        spacing=torch.zeros(points),
        track=None,
        views=views,
        depth=[],
        normal=[],
        reason=reason,
        work=1.0,
        consistent=consistent,
    )


def _entry(**fields) -> dict:
    entry = {
        "flagged_instances": 5,
        "attempted": 1,
        "repaired": 1,
        "added": 12,
        "skipped": {},
        "total_s": 2.25,
        "instances": [{"instance": 3, "class": "sign", "added": 12, "reason": "ok"}],
        "work_budget": None,
        "budget_s": None,
    }
    return {**entry, **fields}


def test_attempt_log_by_hand():
    recs = [_rec(4, 10, [1, 2], "ok"), _rec(0, 3, [5], "explained"), _rec(2, 6, [7], "ok")]
    got = attempt_log(9, "car", [1, 5, 7], recs, 12.5)
    assert got == {
        "instance": 9,
        "class": "car",
        "references": [1, 5, 7],
        "views": [[1, 2], [5], [7]],
        "points": 19,
        "added": 6,
        "work": 12.5,
        "reason": "ok; explained",  # each reason once, in order
    }


def test_repaired_counts_the_instances_that_added():
    assert repaired([{"added": 3}, {"added": 0}, {"added": 1}]) == 2
    assert repaired([]) == 0


def test_log_event_keeps_the_entry_and_a_bounded_pending_log():
    state: dict = {"vad_events": []}
    cfg = VisibilityDensifyConfig()
    for k in range(5):
        log_event(state, _entry(step=k), cfg, 3)
    assert [e["step"] for e in state["vad_events"]] == [0, 1, 2, 3, 4]
    assert [e["step"] for e in state["pending_log"]] == [2, 3, 4]
    last = state["pending_log"][-1]
    assert last["kind"] == "visibility_densification"
    assert last["summary"] == event_summary(state["vad_events"][-1], cfg)


def test_summary_by_hand():
    cfg = VisibilityDensifyConfig(work_budget=2.0, time_budget=0.5)
    line = event_summary(_entry(), cfg)
    assert line == (
        "visibility-aware densification: 5 instances flagged, 1 attempted, 1 repaired (+12 Gaussians), "
        "skipped: none; 2.2 s; added to sign 3 (+12)"
    )
    cut = event_summary(_entry(skipped={"cooldown": 2, "work_budget": 1}, work_budget=4000.0), cfg)
    assert "skipped: 2 cooldown, 1 work_budget;" in cut
    assert "(work budget 4e+03 PatchMatch pixel-sweeps = 2 x training pixels so far;" in cut
    capped = event_summary(_entry(skipped={"time_budget": 3}, budget_s=12.0), cfg)
    assert "(wall-clock cap 12.0 s = 0.5 x training time so far reached:" in capped


def test_summary_names_five_failures_by_four():
    failed = [{"instance": i, "class": "static", "added": 0, "reason": "explained"} for i in range(5)]
    line = event_summary(
        _entry(instances=failed, attempted=5, repaired=0, added=0), VisibilityDensifyConfig()
    )
    assert (
        "5 added nothing (cell 0: explained; cell 1: explained; cell 2: explained; cell 3: explained" in line
    )
    assert "; 1 more in the log), skipped: none" in line and line.endswith("added to none")


def test_labels_and_outcome_names():
    assert (instance_label("sign", 7), instance_label("static", 10)) == ("sign 7", "cell 10")
    assert outcome_name("ok") == "ok"
    assert outcome_name("ok (seen)") == "ok (seen)"
    why = "selection:no_candidates: no view shares >= 2 voxels and a baseline with it"
    assert outcome_name(why) == "selection:no_candidates"
    assert outcome_name(why + " (seen)") == "selection:no_candidates (seen)"
