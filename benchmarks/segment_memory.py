"""Peak memory of each stage of a run on a scene: loading, initialisation, the VAD-GS visibility index.

Each stage's peak resident memory (Linux ``VmHWM``, reset before the stage through
``/proc/self/clear_refs``) and what stays resident after it, on one torch thread. Run on two
lengths of a generated segment (``benchmarks/make_segment.py``) to see what grows with the
frames (docs/scale.md, "Memory as a segment grows")::

    python benchmarks/make_segment.py /tmp/segment_mid --preset mid
    python benchmarks/make_segment.py /tmp/segment_waymo --preset waymo
    python benchmarks/segment_memory.py /tmp/segment_mid     # one process per scene: a peak
    python benchmarks/segment_memory.py /tmp/segment_waymo   # includes what is still resident
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable
from typing import Any

import torch

from vadgs.process import peak_rss_mb, reset_peak_rss


def _status(key: str) -> float:
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith(key):
                return int(line.split()[1]) / 2**20  # kB -> GB
    raise RuntimeError(f"no {key} in /proc/self/status")


def stage(name: str, fn: Callable[[], Any]) -> Any:
    """Run ``fn``, print its seconds, its peak resident GB and the GB resident after it."""
    reset_peak_rss()
    t = time.perf_counter()
    out = fn()
    dt = time.perf_counter() - t
    print(f"  {name:24s} {dt:7.1f} s  peak {peak_rss_mb() / 1024:5.2f} GB  after {_status('VmRSS'):5.2f} GB")
    return out


def main() -> None:
    """Measure every scene given."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scenes", nargs="+")
    ap.add_argument("--scale", type=float, default=0.5)
    args = ap.parse_args()
    torch.set_num_threads(1)
    from vadgs.data import load_scene
    from vadgs.train.init import InitConfig, init_gaussians
    from vadgs.train.vad.visibility import build_visibility_index

    for path in args.scenes:
        scene = stage("load_scene", lambda path=path: load_scene(path, scale=args.scale))
        print(f"{path}: {len(scene.frames)} frames, {scene.num_views} views")
        stage("init_gaussians", lambda scene=scene: init_gaussians(scene, InitConfig()))
        stage("build_visibility_index", lambda scene=scene: build_visibility_index(scene))


if __name__ == "__main__":
    main()
