"""How each stage's cost grows with a segment: frames, resolution (docs/scale.md, issue 40).

For every scene and working scale given, one fresh process (one torch thread) loads the scene,
builds a VAD-GS trainer and measures each stage as a run meets it:

- ``load_scene`` (s); ``init_gaussians`` (s, LiDAR voxelised frame by frame, colours from the images);
- ``build_visibility_index`` (s: voxels and visibility sets of every training sweep);
- ``zbuffer``: the voxel z-buffer of one view (ms a call, ``rasterize_voxels`` as the index calls it);
- ``incomplete``: the per-step incompleteness test of the trained view (ms a call, ``find_incomplete``);
- ``step``: one training step with VAD-GS attached (ms, median of the steps after the first two,
  which build the index and the first z-buffers);
- ``instance``: one (instance, reference) reconstruction at an event (s: the event's
  ``plan_matches``, ``match_plans`` and ``finish_match`` over its pairs: view selection, crops,
  PatchMatch, consistency, fusion), at an event after the steps above; the event
  tests the views the loop trained (a real run's event, after five sampling cycles, has tested
  every view from the loop's renders) and reconstructs at most ``--instances``;
- ``eval_view``: the evaluation of one test view (s a view, ``evaluate`` on ``--eval-views`` views);
- the peak resident memory of the steps (with everything before them: initialisation, the
  index), of the event alone (``VmHWM`` reset before it: the resident model and index included),
  and of the whole process.

Times are CPU seconds of the process (``time.process_time``, one torch thread): on a shared
machine they move far less with the load than wall times do (the steps' wall time is kept too,
``step_wall_ms``, with the load average).

Then, over the scenes of each scale, a least-squares fit of ``log cost = a + b log frames`` gives
each stage's exponent ``b`` (0: flat, 1: linear in the frames), printed as a table and drawn as a
log-log plot::

    python benchmarks/make_segment.py /tmp/segment_25 --preset waymo --frames 25   # and 50, 100, 200
    python benchmarks/segment_scale.py /tmp/segment_25 /tmp/segment_mid /tmp/segment_100 \\
        /tmp/segment_waymo --scales 0.5 0.25 --json runs/scale.json --plot docs/img/segment_scale.png

``--json`` keeps each process's measurements (re-plot with ``--from-json``).
"""

from __future__ import annotations

import argparse
import contextlib
import importlib
import json
import math
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import torch

# (module, function, label): each call timed where the run makes it
_TIMED = [
    ("vadgs.train.trainer", "init_gaussians", "init"),
    ("vadgs.train.vad.strategy", "build_visibility_index", "index"),
    ("vadgs.train.vad.visibility", "rasterize_voxels", "zbuffer"),
    ("vadgs.train.vad.detect", "find_incomplete", "incomplete"),
    ("vadgs.train.vad.event", "plan_matches", "plan"),  # an event's pairs: planned per instance,
    ("vadgs.train.vad.event", "match_plans", "match"),  # matched together,
    ("vadgs.train.vad.event", "finish_match", "finish"),  # fused one by one
]
STAGES = ["load", "init", "index", "zbuffer", "incomplete", "step", "instance", "eval_view"]
PEAKS = ["train_peak_gb", "event_peak_gb", "peak_rss_gb"]
UNITS = {"load": "s", "init": "s", "index": "s", "zbuffer": "ms", "incomplete": "ms", "step": "ms",
         "instance": "s", "eval_view": "s"}  # fmt: skip


@contextlib.contextmanager
def _timed(calls: dict[str, list[float]]):
    saved = []
    for mod_name, fn_name, label in _TIMED:
        mod = importlib.import_module(mod_name)
        fn = getattr(mod, fn_name)
        rec = calls.setdefault(label, [])

        def wrapped(*args, _fn=fn, _rec=rec, **kwargs):
            t = time.process_time()
            out = _fn(*args, **kwargs)
            _rec.append(time.process_time() - t)
            return out

        saved.append((mod, fn_name, fn))
        setattr(mod, fn_name, wrapped)
    try:
        yield
    finally:
        for mod, fn_name, fn in saved:
            setattr(mod, fn_name, fn)


def measure(path: str, scale: float, steps: int, instances: int, eval_views: int) -> dict[str, Any]:
    """The stages of one scene at one working scale, in this process."""
    from vadgs.data import load_scene
    from vadgs.train.config import TrainConfig
    from vadgs.train.results.evaluate import evaluate
    from vadgs.train.trainer import Trainer
    from vadgs.train.vad import VisibilityDensifyConfig

    torch.set_num_threads(1)
    calls: dict[str, list[float]] = {}
    t = time.process_time()
    scene = load_scene(path, scale=scale)
    load_s = time.process_time() - t
    h, w = scene.image_size(0)
    vad = VisibilityDensifyConfig(every_cycles=10**6, max_instances=instances, work_budget=None)
    config = TrainConfig(iterations=10**6, checkpoint_every=0, vad=vad)
    with _timed(calls):
        trainer = Trainer(scene, config, progress=False)
        step_s, step_wall = [], []
        for _ in range(steps):
            t, wall = time.process_time(), time.perf_counter()
            trainer.train_step()
            step_s.append(time.process_time() - t)
            step_wall.append(time.perf_counter() - wall)
        train_peak = _hwm_gb()
        _reset_hwm()
        strategy = trainer.strategy
        detect = strategy.detect
        # the event tests the views the loop trained (a real run's event has tested them all)
        strategy.detect = lambda views=None, renders=None, tests=None: detect(
            sorted(tests or {}), renders, tests
        )
        t = time.process_time()
        event = strategy.densify(trainer.model.params, trainer.optimizer, trainer.state, trainer.step)
        event_s = time.process_time() - t
        event_peak = _hwm_gb()
        strategy.detect = detect
    views = scene.test_views[:: max(1, len(scene.test_views) // eval_views)][:eval_views]
    t = time.process_time()
    evaluate(trainer.model, scene, views, config.raster, with_lpips=False)
    eval_s = (time.process_time() - t) / len(views)
    pairs = len(calls["plan"])  # each pair's share of the event's batched reconstruction
    share = sum(sum(calls[k]) for k in ("plan", "match", "finish")) / max(pairs, 1)
    calls["instance"] = [share] * pairs
    med = {k: statistics.median(v) if v else float("nan") for k, v in calls.items()}
    return {
        "scene": path,
        "frames": len(scene.frames),
        "views": scene.num_views,
        "training_views": len(scene.train_views),
        "scale": scale,
        "size_wh": [w, h],
        "gaussians": trainer.model.num_gaussians,
        "voxels": len(strategy.prepare().grid),
        "load": load_s,
        "init": sum(calls["init"]),
        "index": sum(calls["index"]),
        "zbuffer": 1e3 * med["zbuffer"],
        "zbuffer_calls": len(calls["zbuffer"]),
        "incomplete": 1e3 * med["incomplete"],
        "step": 1e3 * statistics.median(step_s[2:] or step_s),
        "step_wall_ms": 1e3 * statistics.median(step_wall[2:] or step_wall),
        "steps": steps,
        "instance": med["instance"],
        "instance_calls": len(calls["instance"]),
        "event_s": event_s,
        "event_attempted": event["attempted"],
        "eval_view": eval_s,
        "eval_views": len(views),
        "train_peak_gb": train_peak,
        "event_peak_gb": event_peak,
        "peak_rss_gb": max(train_peak, event_peak, _hwm_gb()),
        "load_average": os.getloadavg()[0],
    }


def _hwm_gb() -> float:
    from vadgs.process import peak_rss_mb

    return peak_rss_mb() / 1024


def _reset_hwm() -> None:
    from vadgs.process import reset_peak_rss

    reset_peak_rss()  # the peak from here on


def fit_exponent(frames: list[float], cost: list[float]) -> float:
    """Least-squares slope of ``log cost`` against ``log frames`` (nan with fewer than two points)."""
    pts = [(math.log(f), math.log(c)) for f, c in zip(frames, cost) if c > 0 and math.isfinite(c)]
    if len(pts) < 2:
        return float("nan")
    mx = sum(x for x, _ in pts) / len(pts)
    my = sum(y for _, y in pts) / len(pts)
    sxx = sum((x - mx) ** 2 for x, _ in pts)
    return sum((x - mx) * (y - my) for x, y in pts) / sxx if sxx > 0 else float("nan")


def report(rows: list[dict[str, Any]], plot: str | None) -> str:
    """The table of costs and fitted exponents (markdown), and the log-log plot."""
    lines = []
    scales = sorted({r["scale"] for r in rows}, reverse=True)
    for scale in scales:
        sub = sorted((r for r in rows if r["scale"] == scale), key=lambda r: r["frames"])
        w, h = sub[0]["size_wh"]
        lines.append(f"\n{w}x{h} (scale {scale}):\n")
        lines.append("| stage | " + " | ".join(f"{r['frames']} frames" for r in sub) + " | exponent |")
        lines.append("|---|" + "---:|" * (len(sub) + 1))
        for stage in [*STAGES, *PEAKS]:
            unit = UNITS.get(stage, "GB")
            vals = [r.get(stage, float("nan")) for r in sub]
            b = fit_exponent([r["frames"] for r in sub], vals)
            cells = " | ".join(f"{v:.3g}" for v in vals)
            lines.append(f"| {stage} ({unit}) | {cells} | {b:.2f} |")
        lines.append("| voxels | " + " | ".join(str(r["voxels"]) for r in sub) + " | |")
        lines.append("| Gaussians | " + " | ".join(str(r["gaussians"]) for r in sub) + " | |")
    if plot:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
        from matplotlib.ticker import NullFormatter

        fig, axes = plt.subplots(1, len(scales), figsize=(8.5 * len(scales), 4.5), squeeze=False)
        for ax, scale in zip(axes[0], scales):
            sub = sorted((r for r in rows if r["scale"] == scale), key=lambda r: r["frames"])
            frames = [r["frames"] for r in sub]
            for k, stage in enumerate([*STAGES, *PEAKS]):
                vals = [r.get(stage, float("nan")) for r in sub]
                b = fit_exponent(frames, vals)
                unit = UNITS.get(stage, "GB")
                style = "o-" if stage in STAGES else "s--"
                ax.plot(frames, vals, style, color=f"C{k % 10}", label=f"{stage} ({unit}): b={b:.2f}")
            w, h = sub[0]["size_wh"]
            ax.set(xscale="log", yscale="log", xlabel="frames (5 cameras each)", title=f"{w}x{h}")
            ax.set_xticks(frames, [str(f) for f in frames])
            ax.xaxis.set_minor_formatter(NullFormatter())
            ax.grid(True, which="both", alpha=0.3)
            ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0))
        fig.suptitle("cost of each stage against the segment's length (log-log; b: fitted exponent)")
        fig.tight_layout()
        fig.savefig(plot, dpi=90)
    return "\n".join(lines)


def main() -> None:
    """Measure every scene at every scale (one process each), then fit and plot."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scenes", nargs="*")
    ap.add_argument("--scales", type=float, nargs="+", default=[0.5, 0.25])
    ap.add_argument("--steps", type=int, default=12)
    ap.add_argument("--instances", type=int, default=3)
    ap.add_argument("--eval-views", type=int, default=3)
    ap.add_argument("--json", help="write (or with --from-json read) the measurements here")
    ap.add_argument("--from-json", action="store_true", help="only fit and plot the --json file")
    ap.add_argument("--plot", help="the log-log PNG")
    ap.add_argument("--one", nargs=2, metavar=("SCENE", "SCALE"), help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.one:
        row = measure(args.one[0], float(args.one[1]), args.steps, args.instances, args.eval_views)
        print(json.dumps(row))
        return
    if args.from_json:
        rows = json.loads(Path(args.json).read_text())
    else:
        rows = []
        for scale in args.scales:
            for path in args.scenes:
                cmd = [sys.executable, __file__, "--one", path, str(scale), "--steps", str(args.steps),
                       "--instances", str(args.instances), "--eval-views", str(args.eval_views)]  # fmt: skip
                t = time.perf_counter()
                run = subprocess.run(cmd, capture_output=True, text=True)
                if run.returncode:
                    raise SystemExit(f"{path} at scale {scale} failed:\n{run.stderr[-3000:]}")
                rows.append(json.loads(run.stdout.strip().splitlines()[-1]))
                print(f"{path} x{scale}: {time.perf_counter() - t:.0f} s", flush=True)
                if args.json:
                    Path(args.json).write_text(json.dumps(rows, indent=1))
    print(report(rows, args.plot))


if __name__ == "__main__":
    main()
