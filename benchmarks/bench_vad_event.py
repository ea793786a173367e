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

- ``legacy``: the event before issue 21, as of commit ``274c932`` (render every view for
  detection, at most 8 instances, 2 references each, PatchMatch on full crops at the scene's
  resolution or finer, re-render after every addition). Its code is not kept in the tree: the
  ``vadgs`` package of that commit is read from the git history (``git archive``) into
  ``runs/bench_vad_event/vadgs_274c932/`` once, imported as ``vadgs_274c932`` (its own scene
  loader, visibility index, PatchMatch and densification ops), and given today's trainer state,
  optimizer, render function and base strategy. Without that commit in the history (a shallow
  clone: ``git fetch --unshallow``) the legacy case is skipped with that message;
- ``current``: :class:`vadgs.train.vad.VisibilityAwareDensification` with its defaults, every
  flagged instance (no time budget, for a fixed amount of work).

``extra_info`` holds the instances attempted and reconstructed (MVS run and points kept),
Gaussians added, and the seconds per attempted / per reconstructed instance; the summary test
prints the ratios of the two paths' median per-instance costs.
"""

from __future__ import annotations

import dataclasses
import importlib
import io
import json
import os
import re
import shutil
import statistics
import subprocess
import sys
import tarfile
import tempfile
from pathlib import Path

import pytest
import torch

from vadgs.data import load_scene
from vadgs.train.config import TrainConfig
from vadgs.train.trainer import Trainer
from vadgs.train.vad import VisibilityDensifyConfig

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
SHARED = Path(os.environ.get("VADGS_SHARED", ROOT.parent / "shared")) / "data"
CACHE = ROOT / "runs" / "bench_vad_event"
ROUNDS = int(os.environ.get("VADGS_BENCH_ROUNDS", "3"))
PREP_STEPS = 300
RESULTS: dict[tuple[str, str], list[dict]] = {}
LEGACY_REV = "274c932"  # the last commit before issue 21 (docs/benchmarks.md)
LEGACY_PKG = f"vadgs_{LEGACY_REV}"


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


def legacy_package():
    """``vadgs`` as of :data:`LEGACY_REV`, imported as ``vadgs_274c932`` from the git history.

    Its ``.py`` files are extracted once (``git archive``) into ``runs/bench_vad_event/`` with
    their ``vadgs`` imports renamed, so the old event runs on its own code beside today's package.

    Raises:
        RuntimeError: when the commit is not in this checkout's history (e.g. a shallow clone).
    """
    if LEGACY_PKG in sys.modules:
        return sys.modules[LEGACY_PKG]
    dest = CACHE / LEGACY_PKG
    if not (dest / LEGACY_PKG / "__init__.py").is_file():
        git = ["git", "-C", str(ROOT)]
        known = subprocess.run([*git, "cat-file", "-e", f"{LEGACY_REV}^{{commit}}"], capture_output=True)
        if known.returncode:
            raise RuntimeError(
                f"the legacy event needs commit {LEGACY_REV} in the git history of {ROOT} "
                "(a shallow clone lacks it: git fetch --unshallow)"
            )
        sources = [*git, "archive", "--format=tar", LEGACY_REV, ":(glob)vadgs/**/*.py"]
        tar = subprocess.run(sources, capture_output=True, check=True).stdout
        CACHE.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(dir=CACHE))
        with tarfile.open(fileobj=io.BytesIO(tar)) as tf:
            tf.extractall(tmp, filter="data")
        (tmp / "vadgs").rename(tmp / LEGACY_PKG)
        for f in (tmp / LEGACY_PKG).rglob("*.py"):
            text = re.sub(r"^(\s*)(from|import) vadgs\b", rf"\1\2 {LEGACY_PKG}", f.read_text(), flags=re.M)
            f.write_text(text)
        shutil.rmtree(dest, ignore_errors=True)
        tmp.rename(dest)
    sys.path.insert(0, str(dest))
    return importlib.import_module(LEGACY_PKG)


def _legacy_scene(name: str):
    """The scene as the legacy path loads it (its strategy takes its own ``Scene`` type)."""
    return importlib.import_module(f"{LEGACY_PKG}.data").load_scene(SHARED / name, scale=0.5)


def _legacy_strategy(trainer: Trainer, index):
    """The legacy strategy on ``trainer``'s loop (render, steps, generator, base) and ``index``."""
    legacy_package()
    old = importlib.import_module(f"{LEGACY_PKG}.train.vad")
    c = trainer.strategy.context
    ctx = old.StrategyContext(c.render, c.total_steps, c.steps_per_cycle, c.generator, c.track_nodes)
    config = old.VisibilityDensifyConfig()
    return old.VisibilityAwareDensification(index.scene, ctx, config, base=trainer.strategy.base, index=index)


_INDEX: dict[str, object] = {}


def _warm_index(name: str, scene, legacy: bool):
    """Each path's visibility index with every training view's voxel depth cached (as in a run)."""
    key = f"{name}:{legacy}"
    if key not in _INDEX:
        if legacy:
            legacy_package()
            build_visibility_index = importlib.import_module(
                f"{LEGACY_PKG}.train.reconstruct"
            ).build_visibility_index
            scene = _legacy_scene(name)  # the legacy strategy takes its own Scene type
        else:
            from vadgs.train.vad import build_visibility_index
        index = build_visibility_index(scene, 0.2)
        for v in scene.train_views:
            index.voxel_depth(v)
            index.instances(v)
        _INDEX[key] = index
    return _INDEX[key]


@pytest.mark.parametrize("path", ["legacy", "current"])
def test_event(benchmark, prepared, path):
    name, scene, ckpt = prepared
    if path == "legacy":
        try:
            legacy_package()
        except RuntimeError as e:
            pytest.skip(str(e))
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
