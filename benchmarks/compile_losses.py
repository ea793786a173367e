"""The step's loss glue under ``torch.compile``: kernels and CPU time against eager (issue 48 item 3).

The loss terms of a VAD-GS step at the benchmark's size (240x144: the colour loss with its SSIM,
the LiDAR depth loss, the soft depth and normal losses on priors; random renders and targets of
those shapes), forward and backward, eager against ``torch.compile`` (inductor)::

    OMP_NUM_THREADS=1 PYTHONPATH=. python benchmarks/compile_losses.py

Eager: aten ops counted (``tests/launch_count.py``: one op = one kernel launch on a GPU).
Compiled: the kernels inductor generated (``torch._inductor.metrics.generated_kernel_count``:
on a GPU, one Triton kernel each) plus the convolutions it leaves to aten (2 forward, 2 backward).
CPU times are medians of ``--reps`` forward and backward passes after the compile; the compile's
own time is printed. Not wired into the trainer: a measurement of the option.
"""

from __future__ import annotations

import argparse
import importlib.util
import sys
import time
from pathlib import Path

import torch

REPO = Path(__file__).resolve().parents[1]


def _counter():
    spec = importlib.util.spec_from_file_location("_launch_count", REPO / "tests" / "launch_count.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules["_launch_count"] = module
    spec.loader.exec_module(module)
    return module.LaunchCounter


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--reps", type=int, default=30)
    ap.add_argument("--size", type=int, nargs=2, default=(144, 240), metavar=("H", "W"))
    args = ap.parse_args()
    from torch._inductor import metrics

    from vadgs.train import losses as L

    g = torch.Generator().manual_seed(0)
    h, w = args.size
    pred, image = torch.rand(1, 3, h, w, generator=g), torch.rand(1, 3, h, w, generator=g)
    depth = torch.rand(1, 1, h, w, generator=g) * 10 + 1
    normals = torch.nn.functional.normalize(torch.randn(1, 3, h, w, generator=g), dim=1)
    some = torch.rand(1, 1, h, w, generator=g)
    prior = torch.where(some > 0.5, some * 20, 0.0)
    lidar = torch.where(some > 0.9, some * 20, 0.0)
    targets = L.GeometryTargets(depth=prior, normal=torch.nn.functional.normalize(torch.randn_like(normals)))
    weights = {"soft": 0.1, "hard": 0.1, "normal": 0.05}

    def losses(p: torch.Tensor, d: torch.Tensor, n: torch.Tensor) -> torch.Tensor:
        terms = {"color": L.color_loss(p, image, 0.2), "lidar": 0.05 * L.depth_loss(d, lidar)}
        terms.update(L.geometric_losses(targets, d, n, weights))
        return torch.stack(list(terms.values())).sum()

    def inputs() -> list[torch.Tensor]:
        return [x.clone().requires_grad_() for x in (pred, depth, normals)]

    with _counter()() as c:
        losses(*inputs()).backward()
    compiled = torch.compile(losses)
    metrics.reset()
    t = time.perf_counter()
    compiled(*inputs()).backward()
    compile_s = time.perf_counter() - t
    kernels = metrics.generated_kernel_count + 4  # + the two convolutions forward and backward

    def median_ms(fn) -> float:
        times = []
        for _ in range(args.reps):
            a = inputs()
            t0 = time.perf_counter()
            fn(*a).backward()
            times.append(time.perf_counter() - t0)
        return 1000 * sorted(times)[len(times) // 2]

    a, b = inputs(), inputs()
    va, vb = losses(*a), compiled(*b)
    va.backward()
    vb.backward()
    grad = max(float((x.grad - y.grad).abs().max()) for x, y in zip(a, b))
    print(f"loss terms of a step at {w}x{h}, forward and backward")
    print("| | kernels | CPU ms (median) |")
    print("|---|---|---|")
    print(f"| eager | {c.launches} | {median_ms(losses):.1f} |")
    print(f"| torch.compile (inductor) | {kernels} | {median_ms(compiled):.1f} |")
    diff = float((va - vb).detach().abs())
    print(f"compile: {compile_s:.1f} s; |loss difference| {diff:.2g}, max |gradient difference| {grad:.2g}")


if __name__ == "__main__":
    main()
