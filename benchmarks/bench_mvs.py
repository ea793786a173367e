"""Benchmarks of vadgs.mvs: Middlebury Motorcycle vs StereoSGBM, street_a/b, a moving car, fountain-P11.

    VADGS_BENCH_THREADS=1 pytest benchmarks/bench_mvs.py --benchmark-enable \
        --benchmark-columns=min,median,max,rounds -s

Accuracy numbers go to ``benchmark.extra_info`` and to the JSON file ``$VADGS_BENCH_MVS_OUT``
(default ``/tmp/bench_mvs.json``); ``docs/benchmarks.md`` reports them. Seeded
(``PatchMatchConfig.seed``). Needs ``../shared`` for everything but Middlebury.
``VADGS_BENCH_THREADS=1`` sets ``torch.set_num_threads(1)``: on a loaded 2-core machine the
small ops of PatchMatch run far faster on one intra-op thread.
"""

from __future__ import annotations

import importlib.util
import json
import os
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch

from vadgs.mvs import FusionConfig, PatchMatchConfig, fuse_depth_maps, geometric_consistency, patchmatch

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared" / "data"
OUT = Path(os.environ.get("VADGS_BENCH_MVS_OUT", "/tmp/bench_mvs.json"))

if os.environ.get("VADGS_BENCH_THREADS"):
    torch.set_num_threads(int(os.environ["VADGS_BENCH_THREADS"]))


def _example(name: str):
    key = f"_vadgs_example_{name}"
    if key not in sys.modules:
        spec = importlib.util.spec_from_file_location(key, REPO / "examples" / f"{name}.py")
        sys.modules[key] = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(sys.modules[key])
    return sys.modules[key]


def _record(key: str, value: dict) -> None:
    data = json.loads(OUT.read_text()) if OUT.exists() else {}
    data[key] = value
    OUT.write_text(json.dumps(data, indent=1))


def _sgbm_ms(mb, left, right, n: int = 7) -> float:
    times = []
    for _ in range(n):
        t0 = time.perf_counter()
        mb.sgbm(left, right)
        times.append(time.perf_counter() - t0)
    return statistics.median(times[1:]) * 1e3


def test_middlebury_vs_sgbm(benchmark):
    mb = _example("mvs_middlebury")
    left, right, gt = mb.load_motorcycle()
    sgbm_ms = _sgbm_ms(mb, left, right)
    disp, ok, raw = benchmark.pedantic(mb.patchmatch_stereo, args=(left, right), rounds=1, iterations=1)
    pm_s = benchmark.stats.stats.median
    sgbm_ms_after = _sgbm_ms(mb, left, right)
    res = {
        "patchmatch_raw": mb.metrics(raw, gt),
        "patchmatch_lr_fill": mb.metrics(disp, gt),
        "patchmatch_lr_checked": mb.metrics(np.where(ok, raw, np.nan), gt),
        "sgbm": mb.metrics(mb.sgbm(left, right), gt),
        "patchmatch_seconds_both_directions": pm_s,
        "sgbm_ms_median": [sgbm_ms, sgbm_ms_after],
        "time_ratio": pm_s * 1e3 / statistics.mean([sgbm_ms, sgbm_ms_after]),
        "threads": torch.get_num_threads(),
    }
    benchmark.extra_info.update(res)
    _record("middlebury", res)
    assert res["patchmatch_lr_fill"]["bad2"] < res["sgbm"]["bad2"]


@pytest.mark.skipif(not (SHARED / "street_a").is_dir(), reason="needs ../shared/data/street_a")
@pytest.mark.parametrize("levels", [2, 1])
def test_patchmatch_speed_480x288_4_sources(benchmark, levels):
    """One 480x288 reference, 4 sources, full iterations + cost filtering (street_a frame 20).

    ``levels=2`` is the default coarse-to-fine search, ``levels=1`` the single-scale reference.
    """
    import dataclasses

    st = _example("mvs_street")
    mb = _example("mvs_middlebury")
    b = st.batch(st.StreetScene(SHARED / "street_a"), [20])
    config = dataclasses.replace(st.CONFIG, pyramid_levels=levels)
    args = (b["img"], b["simg"], b["K"], b["sK"], b["w2c"], b["sw2c"], st.DEPTH_RANGE, config)
    left, right, _ = mb.load_motorcycle()
    sgbm_before = _sgbm_ms(mb, left, right)
    res_pm = benchmark.pedantic(patchmatch, args=args, rounds=3, iterations=1, warmup_rounds=1)
    sgbm_after = _sgbm_ms(mb, left, right)
    res = {
        "median_s": benchmark.stats.stats.median,
        "min_s": benchmark.stats.stats.min,
        "sgbm_motorcycle_ms": [sgbm_before, sgbm_after],
        "threads": torch.get_num_threads(),
        "raw": st.depth_accuracy(res_pm.raw_depth, b["depth"]),
        "cost_filtered": st.depth_accuracy(res_pm.depth, b["depth"]),
    }
    benchmark.extra_info.update(res)
    _record(f"speed_480x288_4src_levels{levels}", res)


@pytest.mark.parametrize("scene", ["street_a", "street_b"])
def test_street_accuracy(benchmark, scene):
    if not (SHARED / scene).is_dir():
        pytest.skip(f"needs ../shared/data/{scene}")
    st = _example("mvs_street")
    sc = st.StreetScene(SHARED / scene)
    metrics, *_ = benchmark.pedantic(st.run_street, args=(sc, 20), rounds=1, iterations=1)
    benchmark.extra_info.update(metrics)
    _record(f"{scene}_frame20", metrics)


@pytest.mark.skipif(not (SHARED / "street_a").is_dir(), reason="needs ../shared/data/street_a")
def test_moving_car_object_frame(benchmark):
    st = _example("mvs_street")
    sc = st.StreetScene(SHARED / "street_a")
    frame = max(range(4, 36, 4), key=lambda f: int((sc.load(f)[2] == st.largest_moving_car(sc, f)).sum()))
    metrics = benchmark.pedantic(st.run_car, args=(sc, frame), rounds=1, iterations=1)
    metrics["frame"] = frame
    benchmark.extra_info.update(metrics)
    _record("street_a_moving_car", metrics)


def _read_fountain(root: Path, i: int, scale: int = 8):
    from PIL import Image

    from vadgs.geometry import scale_intrinsics

    lines = (root / "gt_dense_cameras" / f"{i:04d}.jpg.camera").read_text().split("\n")
    vals = [list(map(float, ln.split())) for ln in lines if ln.strip()]
    K = torch.tensor(vals[0:3])
    R = torch.tensor(vals[4:7])  # camera-to-world rotation
    C = torch.tensor(vals[7])
    w, h = (int(v) for v in vals[8])
    img = (
        Image.open(root / "images" / f"{i:04d}.jpg")
        .convert("RGB")
        .resize((w // scale, h // scale), Image.BILINEAR)
    )
    image = torch.from_numpy(np.array(img)).permute(2, 0, 1).float() / 255
    w2c = torch.eye(4)
    w2c[:3, :3] = R.T
    w2c[:3, 3] = -R.T @ C
    return image, scale_intrinsics(K, 1 / scale), w2c


@pytest.mark.skipif(not (SHARED / "real" / "fountain-P11").is_dir(), reason="needs fountain-P11")
def test_fountain(benchmark):
    root = SHARED / "real" / "fountain-P11"
    views = [_read_fountain(root, i) for i in range(11)]
    refs = [3, 4, 5, 6, 7]
    srcs = [[r - 2, r - 1, r + 1, r + 2] for r in refs]
    img = torch.stack([views[r][0] for r in refs])
    K = torch.stack([views[r][1] for r in refs])
    w2c = torch.stack([views[r][2] for r in refs])
    simg = torch.stack([torch.stack([views[s][0] for s in ss]) for ss in srcs])
    sK = torch.stack([torch.stack([views[s][1] for s in ss]) for ss in srcs])
    sw2c = torch.stack([torch.stack([views[s][2] for s in ss]) for ss in srcs])
    cfg = PatchMatchConfig(iterations=3, sigma_color=0.1)
    res = benchmark.pedantic(
        patchmatch, args=(img, simg, K, sK, w2c, sw2c, (2.0, 40.0), cfg), rounds=1, iterations=1
    )
    # each reference checked against the depth maps of the other four references
    others = [[j for j in range(len(refs)) if j != i] for i in range(len(refs))]
    cons = geometric_consistency(
        res.depth, K, w2c, torch.stack([res.depth[o] for o in others]), torch.stack([K[o] for o in others]),
        torch.stack([w2c[o] for o in others]), max_reproj_error=1.0, max_rel_depth=0.01, min_views=2,
    )  # fmt: skip
    fused = fuse_depth_maps(res.depth, img, K, w2c, normal=res.normal, mask=cons.mask, config=FusionConfig())
    import trimesh

    ply = Path(os.environ.get("VADGS_BENCH_MVS_PLY", "/tmp/fountain_mvs.ply"))
    colors = (fused.colors.clamp(0, 1) * 255).to(torch.uint8).numpy()
    trimesh.PointCloud(fused.points.numpy(), colors=colors).export(ply)
    metrics = {
        "image_size": list(img.shape[-2:]),
        "share_cost_valid": float(res.mask.float().mean()),
        "share_consistent": float(cons.mask.float().mean()),
        "share_consistent_per_ref": [float(m) for m in cons.mask.float().mean((1, 2, 3))],
        "fused_points": int(fused.points.shape[0]),
        "ply": str(ply),
        "seconds_5_refs": benchmark.stats.stats.median,
    }
    benchmark.extra_info.update(metrics)
    _record("fountain", metrics)
    np.save(ply.with_suffix(".depth.npy"), res.depth[2, 0].numpy())
    np.save(ply.with_suffix(".mask.npy"), cons.mask[2, 0].numpy())
