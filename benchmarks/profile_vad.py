"""Where the time of a VAD-GS event and of a training step goes on this machine (CPU), the sizes of
``benchmarks/gpu_check.py``'s CUDA mode (bundled sample at 240x144, VAD-GS attached, torch renderer):

    OMP_NUM_THREADS=1 python benchmarks/profile_vad.py event   # cProfile of one event after 30 steps
    OMP_NUM_THREADS=1 python benchmarks/profile_vad.py step    # aten calls and host reads of a step

``event``: the event's seconds and the cumulative time of its ``plan_matches``, ``match_plans`` and
``finish_match`` (a reconstruction in three parts over the event's pairs), ``patchmatch`` and its
``match_costs`` (``_view_costs`` before issue 48). ``step``: after 40 steps (every training
view's voxel maps cached), the aten calls a step makes (torch.profiler) and the reads of tensor
values by the host (``bool``, ``int``, ``float``, ``item``, ``tolist``: a synchronisation each on a
GPU) by the vadgs file and line that asks for them (docs/benchmarks.md, "The GPU check").
"""

from __future__ import annotations

import argparse
import collections
import cProfile
import pstats
import sys
import time
import traceback
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
import gpu_check  # the check's trainer and event, at its CUDA sizes


def _trainer(steps: int):
    sizes = dict(gpu_check.SIZES["cuda"])
    trainer = gpu_check._vad_trainer("cpu", sizes["ops_scale"], "torch", sizes)
    for _ in range(steps):
        trainer.train_step()
    return trainer


def event() -> None:
    trainer = _trainer(30)
    prof = cProfile.Profile()
    t = time.perf_counter()
    prof.enable()
    ev = gpu_check._event(trainer)
    prof.disable()
    seconds = time.perf_counter() - t
    print(f"event {seconds:.2f} s, {ev['attempted']} instances attempted, {ev['added']} added")
    stats = pstats.Stats(prof).stats
    for name in ("plan_matches", "match_plans", "finish_match", "patchmatch", "match_costs"):
        rows = [(v[1], v[3]) for k, v in stats.items() if k[2] == name]
        calls, cum = sum(r[0] for r in rows), sum(r[1] for r in rows)
        print(f"  {name:22s} {calls:5d} calls  {cum:6.2f} s cumulative")


def step(n: int = 5) -> None:
    trainer = _trainer(40)
    from torch.profiler import ProfilerActivity, profile

    with profile(activities=[ProfilerActivity.CPU]) as prof:
        for _ in range(n):
            trainer.train_step()
    calls = sum(e.count for e in prof.key_averages() if e.key.startswith("aten::"))
    print(f"aten calls a step: {calls / n:.0f}")
    reads: collections.Counter[str] = collections.Counter()
    saved = {}
    for name in ("__bool__", "__int__", "__float__", "__index__", "item", "tolist"):
        saved[name] = orig = getattr(torch.Tensor, name)

        def counted(t, *a, _orig=orig, **k):
            frames = [f for f in traceback.extract_stack()[:-1] if "/vadgs/" in f.filename]
            if frames and "/vadgs/" in traceback.extract_stack()[-2].filename:
                f = frames[-1]
                reads[f"{f.filename.rsplit('/vadgs/', 1)[-1]}:{f.lineno}"] += 1
            return _orig(t, *a, **k)

        setattr(torch.Tensor, name, counted)
    try:
        for _ in range(n):
            trainer.train_step()
    finally:
        for name, orig in saved.items():
            setattr(torch.Tensor, name, orig)
    print(f"host reads a step: {sum(reads.values()) / n:.1f}")
    for where, count in reads.most_common(12):
        print(f"  {count / n:6.1f}  {where}")


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("what", choices=["event", "step"])
    torch.set_num_threads(1)
    {"event": event, "step": step}[ap.parse_args().what]()
