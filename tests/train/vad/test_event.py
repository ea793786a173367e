"""The steps of a VAD-GS event (:mod:`vadgs.train.vad.event`) against hand-computed values: what
its log counts.

The event runs for real (:func:`~vadgs.train.vad.event.run_event` through the strategy's
``densify``) on stand-ins of what it reads: the detection's rows, the index's classes and the
reconstruction of an instance (a few points, no PatchMatch), so that each rule is seen alone.
"""

from __future__ import annotations

from types import SimpleNamespace

import pytest
import torch

import vadgs.train.vad.event as event_module
from vadgs.train.vad import (
    InstanceReconstruction,
    StrategyContext,
    VisibilityAwareDensification,
)
from vadgs.train.vad.incomplete import IncompleteInstances

C0 = 0.28209479177387814  # the SH band-0 constant


# -- an event on stand-ins ---------------------------------------------------------------------------


def _rows(flagged: dict[int, int], view: int = 0) -> IncompleteInstances:
    """One view's detection: every instance of ``flagged`` (id → pixels) flagged."""
    ids = sorted(flagged)
    n = len(ids)
    f = torch.full((n,), float("nan"))
    return IncompleteInstances(
        view=torch.full((n,), view, dtype=torch.int64),
        instance=torch.tensor(ids, dtype=torch.int64),
        flagged=torch.ones(n, dtype=torch.bool),
        depth_ratio=f,
        low_alpha=f,
        foreign=f,
        pixels=torch.tensor([flagged[i] for i in ids], dtype=torch.int64),
        voxel_pixels=torch.zeros(n, dtype=torch.int64),
    )


def _rec(instance: int, points: int, consistent: int, track: int | None = None) -> InstanceReconstruction:
    g = torch.Generator().manual_seed(instance)
    return InstanceReconstruction(
        points=torch.rand(points, 3, generator=g),
        normals=torch.tensor([[0.0, 0.0, 1.0]]).repeat(points, 1),
        colors=torch.full((points, 3), 0.5),
        spacing=torch.full((points,), 0.05),
        track=track,
        views=[0],
        depth=[torch.zeros(1, 4, 4)],
        normal=[torch.zeros(3, 4, 4)],
        reason="ok" if points else "explained",
        work=1.0,
        consistent=consistent,
    )


def _splats(n: int = 4, node_ids: bool = False) -> dict[str, torch.Tensor]:
    """gsplat-layout Gaussians (no optimizer: the event's additions need none)."""
    p = {
        "means": torch.zeros(n, 3),
        "quats": torch.tensor([[1.0, 0, 0, 0]]).repeat(n, 1),
        "scales": torch.zeros(n, 3),
        "opacities": torch.zeros(n),
        "sh0": torch.zeros(n, 1, 3),
        "shN": torch.zeros(n, 0, 3),
    }
    if node_ids:
        p["node_ids"] = torch.full((n,), -1, dtype=torch.int64)
    return p


class _Event:
    """A strategy whose events see ``flagged`` (instance → pixels, every event) and reconstruct each
    instance as ``made[instance] = (points, consistent)`` (default ``(3, 7)``); ``tracks``: the
    moving instances (track id → node)."""

    def __init__(self, monkeypatch, flagged, made=None, tracks=None, **settings):
        tracks = tracks or {}
        settings = {"work_budget": None, "whole_reference": False, "ranking": "pixels", **settings}
        self.strategy = s = VisibilityAwareDensification(**settings)
        s.inputs = SimpleNamespace(
            train_views=(0,),
            tracks=dict.fromkeys(tracks),
            views=[SimpleNamespace(camera="front", frame=0)],
        )
        s.index = SimpleNamespace(
            classes=lambda: dict.fromkeys(flagged, "thing"), cut_by_border=lambda view, inst: False
        )
        s.context = StrategyContext(
            render=lambda v: pytest.fail("the event renders nothing here"),
            total_steps=100,
            steps_per_cycle=1,
            track_nodes=tracks,
        )
        self.state = s.initialize_state()
        self.calls: list[int] = []
        made = made or {}

        def reconstruct(index, ref, instance, *args, **kwargs):
            self.calls.append(instance)
            n, c = made.get(instance, (3, 7))
            return _rec(instance, n, c, track=instance if instance in tracks else None)

        monkeypatch.setattr(event_module, "detect", lambda *a, **k: (_rows(flagged), [0]))
        monkeypatch.setattr(event_module, "reconstruct_instance", reconstruct)

    def run(self, params, step=0) -> dict:
        return self.strategy.densify(params, None, self.state, step)


class TestEventLog:
    def test_points_and_added(self, monkeypatch):
        """``points``: the consistent MVS points of the instance's references; ``added``: the
        Gaussians it got (what remains once the explained points are left out and the rest thinned)."""
        ev = _Event(monkeypatch, {1: 400, 2: 300, 3: 200}, made={1: (20, 500), 2: (0, 80), 3: (0, 0)})
        params = _splats()
        entry = ev.run(params)
        got = {i["instance"]: (i["points"], i["added"], i["reason"]) for i in entry["instances"]}
        assert got == {1: (500, 20, "ok"), 2: (80, 0, "explained"), 3: (0, 0, "explained")}
        assert entry["added"] == 20 == params["means"].shape[0] - 4
        assert entry["attempted"] == 3 and entry["repaired"] == 1
        assert "2 added nothing" in ev.state["pending_log"][-1]["summary"]

    def test_points_sum_over_references(self, monkeypatch):
        ev = _Event(monkeypatch, {1: 400}, made={1: (6, 9)}, references=1)
        assert ev.run(_splats())["instances"][0]["points"] == 9
        monkeypatch.setattr(
            event_module, "pick_references", lambda candidates, *a, **k: [0, 0]
        )  # two references of the one view: two reconstructions
        entry = ev.run(_splats())
        assert (entry["instances"][0]["points"], entry["instances"][0]["added"]) == (18, 12)
