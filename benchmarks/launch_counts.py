"""Kernel launches and host reads of VAD-GS's pieces against issue 48's targets, and their CPU times.

Every aten op counted on the CPU (``tests/launch_count.py``: views left out) is one kernel launch
on a GPU, every read of a tensor value by the host one synchronisation. Three pieces, at the sizes
of the GPU check (``benchmarks/gpu_check.py``, its ``cuda`` sizes: the bundled sample at 240x144,
VAD-GS attached, no work budget, up to 4 instances an event):

- one PatchMatch call (default :class:`~vadgs.mvs.PatchMatchConfig`, one cost chunk as on a GPU;
  a slanted textured plane, 4 sources, 80x112);
- one event after 30 steps, per attempted instance (PatchMatch in one cost chunk, as on a GPU);
- one steady-state training step (after one full sampling cycle, so that every view's caches are
  filled), split into the rasterizer's forward and backward (its calls recorded during the counted
  steps and replayed alone on detached inputs) and everything else (the step's count minus that).

::

    OMP_NUM_THREADS=1 PYTHONPATH=. python benchmarks/launch_counts.py
    OMP_NUM_THREADS=1 PYTHONPATH=. python benchmarks/launch_counts.py --json counts.json

CPU times are medians of ``--reps`` runs after a warm-up, measured without the counter. Run it
from another tree with ``PYTHONPATH=OTHER`` for the figures before a change.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import sys
import time
from pathlib import Path
from typing import Any

import torch

REPO = Path(__file__).resolve().parents[1]
PM_ONE_CHUNK = 1 << 30  # PatchMatchConfig.chunk_size: one chunk per scoring, as on a GPU
TARGETS = {  # issue 48: (launches, host reads); None: no target
    "patchmatch": (1000, None),
    "event_instance": (5000, 25),
    "step_outside": (300, 5),
    "step_rasterizer": (None, None),
}


def _load(name: str, path: Path):
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    spec.loader.exec_module(module)
    return module


_counting = _load("_launch_count", REPO / "tests" / "launch_count.py")
_gpu_check = _load("_gpu_check", REPO / "benchmarks" / "gpu_check.py")


def _rasterizer_counts(calls: list) -> tuple[int, int]:
    """Launches and host reads of the recorded rasterizer calls, forward and backward, replayed alone.

    Each call's tensor inputs are detached (those that required grad require it again), so the
    backward stops at the rasterizer's inputs; the output gradients are made before counting.
    """
    from torch.utils._pytree import tree_leaves, tree_map

    from vadgs.render import rasterize_gaussians

    launches = reads = 0
    for args, kwargs in calls:

        def leaf(t):
            if isinstance(t, torch.Tensor):
                return t.detach().requires_grad_(t.requires_grad)
            return t

        a, k = tree_map(leaf, (args, kwargs))
        with torch.enable_grad():
            with _counting.LaunchCounter() as c:
                out = rasterize_gaussians(*a, **k)
            outs = [t for t in tree_leaves(out) if isinstance(t, torch.Tensor) and t.requires_grad]
            grads = [torch.ones_like(t) for t in outs]
            with _counting.LaunchCounter() as cb:
                torch.autograd.backward(outs, grads)
        launches += c.launches + cb.launches
        reads += c.host_reads + cb.host_reads
    return launches, reads


def patchmatch_call(reps: int) -> dict[str, Any]:
    """One default PatchMatch call, B=1, V=4, 80x112, one cost chunk."""
    from vadgs.mvs import PatchMatchConfig, patchmatch

    pm = _load("_pm_launches", REPO / "benchmarks" / "patchmatch_launches.py")
    args, kw, _ = pm._synthetic(1, 4, (80, 112), False)
    cfg = PatchMatchConfig(chunk_size=pm.ONE_CHUNK)
    with _counting.LaunchCounter() as c:
        patchmatch(*args, cfg, **kw)
    ms = _gpu_check._median_ms(lambda: patchmatch(*args, PatchMatchConfig(), **kw), reps, "cpu")
    return {"launches": c.launches, "host_reads": c.host_reads, "cpu_ms": ms, "per": "call"}


def event_and_step(steps_before_event: int, step_reps: int) -> dict[str, dict[str, Any]]:
    """One event after ``steps_before_event`` steps, then steady-state steps (counted and timed)."""
    from dataclasses import replace

    sizes = dict(_gpu_check.SIZES["cuda"])
    trainer = _gpu_check._vad_trainer("cpu", sizes["ops_scale"], "torch", sizes)
    # PatchMatch scores in one chunk, as on a GPU (the CPU's default cuts a scoring into
    # cache-sized chunks, over all the references of a call: the same values, more launches)
    vad = trainer.strategy.config
    pm = replace(vad.reconstruct.patchmatch, chunk_size=PM_ONE_CHUNK)
    trainer.strategy.config = replace(vad, reconstruct=replace(vad.reconstruct, patchmatch=pm))
    for _ in range(steps_before_event):
        trainer.train_step()
    t = time.perf_counter()
    with _counting.LaunchCounter() as c:
        ev = _gpu_check._event(trainer)
    seconds = time.perf_counter() - t  # with the counter's overhead: an upper bound
    n = max(int(ev["attempted"]), 1)
    out = {
        "event_instance": {
            "launches": c.launches // n,
            "host_reads": c.host_reads // n,
            "cpu_ms": 1000 * seconds / n,
            "per": f"attempted instance ({ev['attempted']} attempted, {ev['added']} Gaussians added; "
            "time with the counter on)",
        }
    }
    # Steady state: after one full sampling cycle every training view's caches are filled.
    for _ in range(len(trainer.train_views)):
        trainer.train_step()
    import vadgs.train.model as model_module

    n_count = 5
    calls: list = []
    real = model_module.rasterize_gaussians

    def spy(*a, **k):
        calls.append((a, k))
        return real(*a, **k)

    model_module.rasterize_gaussians = spy
    try:
        with _counting.LaunchCounter() as c:
            for _ in range(n_count):
                trainer.train_step()
    finally:
        model_module.rasterize_gaussians = real
    inside, inside_reads = _rasterizer_counts(calls)
    ms = _gpu_check._median_ms(trainer.train_step, step_reps, "cpu")
    out["step_outside"] = {
        "launches": (c.launches - inside) // n_count,
        "host_reads": (c.host_reads - inside_reads) // n_count,
        "cpu_ms": ms,
        "per": f"step ({trainer.model.num_gaussians:,} Gaussians; time of the whole step)",
    }
    out["step_rasterizer"] = {
        "launches": inside // n_count,
        "host_reads": inside_reads // n_count,
        "cpu_ms": None,
        "per": f"step: the torch rasterizer, forward and backward ({len(calls) / n_count:g} calls), alone",
    }
    return out


def _table(rows: dict[str, dict[str, Any]]) -> str:
    lines = [
        "| piece | launches | target | host reads | target | CPU ms (median) | per |",
        "|---|---|---|---|---|---|---|",
    ]
    for name, r in rows.items():
        tl, tr = TARGETS[name]

        def fmt(v, t):
            if t is None:
                return f"{v:,}", "–"
            return f"{v:,}", f"≤ {t:,} ({'met' if v <= t else 'not met'})"

        launches, tl_s = fmt(r["launches"], tl)
        reads, tr_s = fmt(r["host_reads"], tr)
        ms = "–" if r["cpu_ms"] is None else f"{r['cpu_ms']:.0f}"
        lines.append(f"| {name} | {launches} | {tl_s} | {reads} | {tr_s} | {ms} | {r['per']} |")
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--reps", type=int, default=5, help="timed runs per piece (median)")
    ap.add_argument("--steps-before-event", type=int, default=30)
    ap.add_argument("--json", type=Path, default=None, help="also write the rows as JSON")
    args = ap.parse_args()
    torch.set_num_threads(1)
    rows = {"patchmatch": patchmatch_call(args.reps)}
    rows.update(event_and_step(args.steps_before_event, args.reps))
    print(_table(rows))
    if args.json is not None:
        args.json.write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
