"""A training step's kernel launches and host reads outside the rasterizer (issue 48, item 3): bounded.

Counted on the CPU with :class:`tests.launch_count.LaunchCounter` (one aten op = one kernel launch
on a GPU, one read of a tensor value by the host = one synchronisation), as
``benchmarks/launch_counts.py`` counts them: the steps' counts minus those of the rasterizer's calls
(forward and backward) replayed alone. A small VAD-GS run (the bundled sample at scale 0.25, no
event in reach), after one full sampling cycle so that every view's caches are filled.
"""

from __future__ import annotations

import torch
from torch.utils._pytree import tree_leaves, tree_map

import vadgs.train.model as model_module
from vadgs.data import load_scene, sample_scene_path
from vadgs.train.config import TrainConfig
from vadgs.train.init import InitConfig
from vadgs.train.trainer import Trainer
from vadgs.train.vad import VisibilityDensifyConfig

from ..launch_count import LaunchCounter

#: issue 48's target for a step outside the rasterizer (host reads and launches, both met at the
#: benchmark's size: 1 read and 298 launches a step), and the launches measured here (230 at
#: this smaller run: SH degree 1, a quarter of the sample's size) with a margin. At the benchmark's
#: size, before issue 48: 41 reads and 835 launches a step; 3 and 420 before the incompleteness
#: test left the step (docs/benchmarks.md).
READS = 5
LAUNCHES = 250


def _replayed(calls: list) -> tuple[int, int]:
    """Launches and reads of the recorded rasterizer calls, forward and backward, replayed alone."""
    launches = reads = 0
    for args, kwargs in calls:
        a, k = tree_map(
            lambda t: t.detach().requires_grad_(t.requires_grad) if isinstance(t, torch.Tensor) else t,
            (args, kwargs),
        )
        with torch.enable_grad():
            with LaunchCounter() as c:
                out = model_module.rasterize_gaussians(*a, **k)
            outs = [t for t in tree_leaves(out) if isinstance(t, torch.Tensor) and t.requires_grad]
            with LaunchCounter() as cb:
                torch.autograd.backward(outs, [torch.ones_like(t) for t in outs])
        launches += c.launches + cb.launches
        reads += c.host_reads + cb.host_reads
    return launches, reads


def test_a_steady_step_outside_the_rasterizer_launches_and_reads_little(monkeypatch):
    scene = load_scene(sample_scene_path(), scale=0.25)
    config = TrainConfig(
        iterations=10**6,
        checkpoint_every=0,
        init=InitConfig(voxel_size=0.6, max_points=1500, max_object_points=150, sh_degree=1),
        vad=VisibilityDensifyConfig(every_cycles=10**6),
    )
    tr = Trainer(scene, config, progress=False)
    for _ in range(len(tr.train_views)):  # every view's caches filled
        tr.train_step()
    calls: list = []
    real = model_module.rasterize_gaussians

    def spy(*a, **k):
        calls.append((a, k))
        return real(*a, **k)

    monkeypatch.setattr(model_module, "rasterize_gaussians", spy)
    n = 3
    with LaunchCounter() as c:
        for _ in range(n):
            tr.train_step()
    monkeypatch.setattr(model_module, "rasterize_gaussians", real)
    inside, inside_reads = _replayed(calls)
    launches, reads = (c.launches - inside) / n, (c.host_reads - inside_reads) / n
    assert reads <= READS, (reads, c.ops.most_common(20))
    print(f"outside the rasterizer: {launches:.0f} launches, {reads:.1f} host reads a step")
    assert launches <= LAUNCHES, (launches, c.ops.most_common(20))
    assert len(tr.state["vad_renders"]) >= n  # the steps did keep their renders for the event's test
