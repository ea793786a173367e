"""One VAD-GS event on street_a / street_b: today's path against the path before issue 21, same run.

    pytest benchmarks/bench_vad_event.py --benchmark-enable -p no:cacheprovider \
        --benchmark-columns=min,median,max,rounds --benchmark-sort=name -s

Setup (outside the timing, once per scene): the street config (``benchmarks/street_config.json``,
240×144, one torch thread) trains 300 steps with the VAD-GS strategy attached but no event
(``every_cycles`` huge), so that the strategy state holds what a real run has before its first
event: the incompleteness tests and renders of the views trained since the last event (new path),
every view's voxel depth cached (both paths; a real run computes them for the voxel-depth prior).
The checkpoint is written once to ``runs/bench_vad_event/`` and reloaded before every round.

Each round runs one event on a fresh copy of that checkpoint:

- ``legacy``: a frozen copy of the event before issue 21 (``benchmarks/legacy_event``: render
  every view for detection, at most 8 instances, 2 references each, PatchMatch on full crops at
  the scene's resolution or finer, re-render after every addition);
- ``current``: :class:`vadgs.train.vad.VisibilityAwareDensification` with its defaults, every
  flagged instance (no time budget, for a fixed amount of work).

``extra_info`` holds the instances attempted and reconstructed (MVS run and points kept),
Gaussians added, and the seconds per attempted / per reconstructed instance; the summary test
prints the ratios of the two paths' median per-instance costs.
"""

from __future__ import annotations

import dataclasses
import json
import os
import statistics
import sys
from pathlib import Path

import pytest
import torch

from vadgs.data import load_scene
from vadgs.train.trainer import TrainConfig, Trainer
from vadgs.train.vad import VisibilityDensifyConfig

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
SHARED = ROOT.parent / "shared" / "data"
CACHE = ROOT / "runs" / "bench_vad_event"
ROUNDS = int(os.environ.get("VADGS_BENCH_ROUNDS", "3"))
PREP_STEPS = 300
RESULTS: dict[tuple[str, str], list[dict]] = {}


def _config() -> TrainConfig:
    cfg = TrainConfig.from_dict(json.loads((ROOT / "benchmarks" / "street_config.json").read_text()))
    return dataclasses.replace(
        cfg, checkpoint_every=0, threads=1, vad=VisibilityDensifyConfig(every_cycles=10**6)
    )


def _checkpoint(name: str) -> Path:
    path = CACHE / f"{name}_{PREP_STEPS}.pt"
    if not path.is_file():
        trainer = Trainer(load_scene(SHARED / name, scale=0.5), _config(), progress=False)
        for _ in range(PREP_STEPS):
            trainer.train_step()
        trainer.save_checkpoint(path)
    return path


@pytest.fixture(scope="module", params=["street_a", "street_b"])
def prepared(request):
    name = request.param
    if not (SHARED / name / "scene.json").is_file():
        pytest.skip(f"needs ../shared/data/{name}")
    torch.set_num_threads(1)
    scene = load_scene(SHARED / name, scale=0.5)
    return name, scene, _checkpoint(name)


def _fresh(scene, ckpt: Path) -> Trainer:
    trainer = Trainer.from_checkpoint(ckpt, scene=scene, progress=False)
    return trainer


def _legacy_strategy(trainer: Trainer, index):
    from benchmarks.legacy_event.vad import StrategyContext
    from benchmarks.legacy_event.vad import VisibilityAwareDensification as Legacy
    from benchmarks.legacy_event.vad import VisibilityDensifyConfig as LegacyConfig

    ctx = trainer.strategy.context
    ctx = StrategyContext(ctx.render, ctx.total_steps, ctx.steps_per_cycle, ctx.generator, ctx.track_nodes)
    legacy = Legacy(trainer.scene, ctx, LegacyConfig(), base=trainer.strategy.base, index=index)
    return legacy


_INDEX: dict[str, object] = {}


def _warm_index(name: str, scene, legacy: bool):
    """Each path's visibility index with every training view's voxel depth cached (as in a run)."""
    key = f"{name}:{legacy}"
    if key not in _INDEX:
        if legacy:
            from benchmarks.legacy_event.reconstruct import build_visibility_index
        else:
            from vadgs.train.reconstruct import build_visibility_index
        index = build_visibility_index(scene, 0.2)
        for v in scene.train_views:
            index.voxel_depth(v)
            index.instances(v)
        _INDEX[key] = index
    return _INDEX[key]


@pytest.mark.parametrize("path", ["legacy", "current"])
def test_event(benchmark, prepared, path):
    name, scene, ckpt = prepared
    index = _warm_index(name, scene, path == "legacy")
    logs: list[dict] = []

    def setup():
        trainer = _fresh(scene, ckpt)
        if path == "legacy":
            strategy = _legacy_strategy(trainer, index)
        else:
            strategy = trainer.strategy
            strategy.index = index
            strategy.config = dataclasses.replace(strategy.config, work_budget=None, time_budget=None)
        return (trainer, strategy), {}

    def run(trainer, strategy):
        state = trainer.state
        state.setdefault("vad_events", [])
        state.setdefault("vad_priors", {})
        state.setdefault("vad_last_done", {})
        event = strategy.densify(trainer.model.params, trainer.optimizer, state, trainer.step)
        logs.append(event)

    benchmark.pedantic(run, setup=setup, rounds=ROUNDS, iterations=1, warmup_rounds=0)
    info = []
    for e in logs:
        attempted = len(e["instances"])
        mvs = sum(1 for i in e["instances"] if i["views"] and any(len(v) > 1 for v in i["views"]))
        info.append(
            {
                "total_s": e["total_s"],
                "detect_s": e["detect_s"],
                "mvs_s": e["mvs_s"],
                "flagged_instances": e["flagged_instances"],
                "attempted": attempted,
                "reconstructed": mvs,
                "with_points": sum(1 for i in e["instances"] if i["points"] > 0),
                "added": e["added"],
                "s_per_attempted": e["total_s"] / max(attempted, 1),
                "s_per_reconstructed": e["total_s"] / max(mvs, 1),
            }
        )
    RESULTS[(name, path)] = info
    med = {k: statistics.median(r[k] for r in info) for k in info[0]}
    benchmark.extra_info.update(med)
    print(f"\n{name} {path}: " + ", ".join(f"{k}={v:.3g}" for k, v in med.items()))


def test_ratio_summary(prepared):
    name = prepared[0]
    old, new = RESULTS.get((name, "legacy")), RESULTS.get((name, "current"))
    if not (old and new):
        pytest.skip("run with the event benchmarks")
    for key in ("s_per_attempted", "s_per_reconstructed"):
        a = statistics.median(r[key] for r in old)
        b = statistics.median(r[key] for r in new)
        print(f"\n{name}: {key}: legacy {a:.2f} s, current {b:.2f} s, ratio {a / b:.1f}x")
