"""AbsRel of the rendered depth against the test frames' own LiDAR, by camera and by LiDAR depth bin.

Where a run's depth is good or bad against the held-out sweeps (``depth.lidar`` of ``vadgs eval``
pools every pixel), one line per run folder or checkpoint: ``camera@lo-hi m: (AbsRel, pixels)``::

    OMP_NUM_THREADS=1 python benchmarks/lidar_depth_bins.py RUN_A/checkpoint.pt RUN_B/checkpoint.pt
"""

from __future__ import annotations

import argparse

import torch

from vadgs.data.lidar import lidar_depth_map
from vadgs.train.results.evaluate import render_test_view
from vadgs.train.run import load_run

BINS_M = [(0, 15), (15, 30), (30, 60), (60, float("inf"))]


def depth_bins(path: str) -> dict[str, tuple[float, int]]:
    """``{"camera@lo-hi m": (AbsRel, LiDAR pixels)}`` of the run's test views."""
    run = load_run(path)
    scene = run.scene
    acc: dict[tuple[str, float], list[float]] = {}
    for v in scene.test_views:
        try:
            lidar = lidar_depth_map(scene, v)
        except FileNotFoundError:  # a frame without a sweep adds nothing (as evaluate's lidar group)
            continue
        depth = render_test_view(run.model, scene, v, run.config.raster).raster.depth.cpu()
        cam = scene.views[v].camera.removesuffix("_camera")
        for lo, hi in BINS_M:
            m = (lidar > lo) & (lidar <= hi)
            if bool(m.any()):
                a = acc.setdefault((cam, lo), [0.0, 0])
                a[0] += float(((depth[m] - lidar[m]).abs() / lidar[m]).sum())
                a[1] += int(m.sum())
    names = {lo: f"{lo}-{hi:g}" for lo, hi in BINS_M}
    return {f"{c}@{names[lo]} m": (round(s / n, 3), int(n)) for (c, lo), (s, n) in sorted(acc.items())}


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("runs", nargs="+", help="run folders or checkpoint.pt files")
    torch.set_num_threads(1)
    for p in ap.parse_args().runs:
        print(p, depth_bins(p))
