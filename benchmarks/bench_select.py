"""Benchmarks of vadgs.select on street_a (needs ../shared; skipped when absent).

    pytest benchmarks/bench_select.py --benchmark-enable --benchmark-columns=min,median,max,rounds

``VADGS_BENCH_THREADS=1`` sets ``torch.set_num_threads(1)`` first (selection is a chain of small
ops: on a loaded 2-core machine intra-op threads mostly wait on each other).
Results and ratios: ``docs/benchmarks.md``.
"""

from __future__ import annotations

import importlib.util
import math
import os
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from vadgs.select import ViewSelectionConfig, ViewSelector, diversity_scores

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared"
SCENE = SHARED / "data" / "street_a"

pytestmark = pytest.mark.skipif(not SCENE.is_dir(), reason="needs ../shared/data/street_a")

if os.environ.get("VADGS_BENCH_THREADS"):
    torch.set_num_threads(int(os.environ["VADGS_BENCH_THREADS"]))


def _example():
    key = "_vadgs_example_select_street"
    if key not in sys.modules:
        spec = importlib.util.spec_from_file_location(key, REPO / "examples" / "select_street.py")
        sys.modules[key] = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(sys.modules[key])
    return sys.modules[key]


@pytest.fixture(scope="module")
def street():
    torch.manual_seed(0)
    ex = _example()
    views = ex.load_street(SCENE)
    return {
        "whole": ex.street_covisibility(views),  # all static pixels, 0.2 m voxels
        "sign": ex.street_covisibility(views, views.instance_id("sign")),
        "car": ex.street_covisibility(views, views.overtaken_car(), object_frame=True),
    }


def naive_pair_scores(covis, eps=0.1):
    """The in-run reference: a Python loop over ordered pairs of views, numpy per pair."""
    V = covis.num_views
    idx = covis.incidence.indices().numpy()
    sets = [idx[1, idx[0] == v] for v in range(V)]
    pts = covis.voxel_centers.double().numpy()
    poses = covis.world_to_cam.double().numpy()
    cams = [np.linalg.inv(p)[:3, 3] for p in poses]
    out = np.zeros((V, V))
    for r in range(V):
        for s in range(V):
            common = np.intersect1d(sets[r], sets[s], assume_unique=True)
            if r == s or len(common) == 0:
                continue
            d_r = np.linalg.norm(pts[common] - cams[r], axis=1)
            d_s = np.linalg.norm(pts[common] - cams[s], axis=1)
            t = poses[r][:3, :3] @ (cams[s] - cams[r])
            rel = poses[r][:3, :3] @ poses[s][:3, :3].T
            sin = np.linalg.norm([rel[2, 1] - rel[1, 2], rel[0, 2] - rel[2, 0], rel[1, 0] - rel[0, 1]]) / 2
            out[r, s] = len(common) / (d_r @ d_s) * math.hypot(t[0], t[1]) / (abs(t[2]) + eps) * sin
    return out


def _refs(covis, min_shared=8):
    return torch.nonzero(covis.visible_counts() >= min_shared).squeeze(1).tolist()


@pytest.mark.parametrize("target", ["sign", "car", "whole"])
def test_score_all_pairs_vectorised(benchmark, street, target):
    covis = street[target]
    out = benchmark.pedantic(diversity_scores, args=(covis,), rounds=5, warmup_rounds=1)
    benchmark.extra_info.update(views=covis.num_views, voxels=covis.num_voxels, nnz=covis.incidence._nnz())
    if target != "whole":
        np.testing.assert_allclose(out.score.numpy(), naive_pair_scores(covis), rtol=2e-3, atol=1e-9)


@pytest.mark.parametrize("target", ["sign", "car", "whole"])
def test_score_all_pairs_naive_loop(benchmark, street, target):
    covis = street[target]
    rounds = 1 if target == "whole" else 3
    benchmark.pedantic(naive_pair_scores, args=(covis,), rounds=rounds, warmup_rounds=0)


@pytest.mark.parametrize("target", ["sign", "car", "whole"])
@pytest.mark.parametrize("max_candidates", [24])
def test_select_every_reference(benchmark, street, target, max_candidates):
    """Scoring and selection for every reference view (all 120 for 'whole'), seeded."""
    covis = street[target]
    refs = list(range(covis.num_views)) if target == "whole" else _refs(covis)

    config = ViewSelectionConfig(max_candidates=max_candidates)

    def run():
        return ViewSelector(config, seed=0).select_all(covis, refs)

    sels = benchmark.pedantic(run, rounds=3, warmup_rounds=1)
    benchmark.extra_info.update(refs=len(refs), complete=sum(s.complete for s in sels))


@pytest.mark.parametrize("method", ["consecutive", "mvsnet", "colmap"])
def test_baseline_every_reference(benchmark, street, method):
    covis = street["whole"]
    selector = ViewSelector(ViewSelectionConfig(method=method))
    benchmark.pedantic(selector.select_all, args=(covis,), rounds=3, warmup_rounds=1)
