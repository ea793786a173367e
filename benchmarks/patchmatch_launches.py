"""Kernel launches, host reads and CPU time of one PatchMatch call, and agreement with another tree.

Every aten op counted on the CPU (``tests/launch_count.py``: views left out) is one kernel launch on
a GPU, every read of a tensor value by the host one synchronisation (issue 48: "PatchMatch as a
few launches per sweep"). ``count`` prints, per problem, the launches and host reads of one default
call (``chunk_size`` one chunk, as on a GPU; and the CPU's default chunking) and the median CPU
time; with ``--old TREE`` the same problems run in a subprocess on that tree's ``vadgs`` (e.g. the
code before the change) and both are printed side by side. ``compare --old TREE`` runs the same
calls in both trees and prints how far the results agree (depth within 1e-3 / 1e-2 relative where
both are valid, masks) and their accuracy against ground truth::

    OMP_NUM_THREADS=1 PYTHONPATH=. python benchmarks/patchmatch_launches.py count --old ../main
    OMP_NUM_THREADS=1 PYTHONPATH=. python benchmarks/patchmatch_launches.py compare --old ../main
    OMP_NUM_THREADS=1 PYTHONPATH=. python benchmarks/patchmatch_launches.py joint   # accuracy

``compare`` includes street_a frame 20 (480x288, 4 sources) and its largest moving car (object
frame, regions) when ``../shared/data/street_a`` is there.
"""

from __future__ import annotations

import argparse
import dataclasses
import importlib.util
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import torch

REPO = Path(__file__).resolve().parents[1]
STREET_A = REPO.parent / "shared" / "data" / "street_a"
ONE_CHUNK = 1 << 30
BASELINES = ((0.15, 0.0, 0.0), (-0.15, 0.0, 0.0), (0.0, 0.12, 0.0), (0.1, 0.1, 0.0))


def _load(name: str, path: Path):
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    spec.loader.exec_module(module)
    return module


def _plane_scene(**kw):
    return _load("_mvs_scenes", REPO / "tests" / "mvs" / "mvs_scenes.py").plane_scene(**kw)


def _synthetic(batch: int, views: int, size: tuple[int, int], regions: bool):
    """A textured slanted plane; with ``regions``: a region, source regions and a partial init."""
    sc = _plane_scene(size=size, baselines=BASELINES[:views], normal=(0.35, -0.25, -1.0), seed=1)

    def rep(t):
        return t.repeat(batch, *([1] * (t.ndim - 1)))

    args = (rep(sc.image), rep(sc.src_images), rep(sc.K), rep(sc.src_K), rep(sc.world_to_cam))
    args = (*args, rep(sc.src_world_to_cam), (1.0, 10.0))
    kw = {}
    if regions:
        h, w = size
        mask = torch.zeros(batch, 1, h, w, dtype=torch.bool)
        mask[..., h // 5 : -h // 5, w // 6 : -w // 6] = True
        init = rep(sc.depth).clone()
        init[..., : h // 2, :] = 0
        kw = dict(
            mask=mask,
            src_masks=torch.ones(batch, views, 1, h, w, dtype=torch.bool),
            init_depth=init,
            init_normal=rep(sc.normal.reshape(1, 3, 1, 1).expand(1, 3, h, w)).clone(),
        )
    return args, kw, rep(sc.depth)


COUNT_PROBLEMS = {
    f"B={b} V={v} {s[0]}x{s[1]}{' +regions,init' if r else ''}": (b, v, s, r)
    for r in (False, True)
    for b, v, s in ((1, 1, (40, 56)), (3, 4, (40, 56)), (1, 4, (80, 112)), (1, 4, (160, 224)))
}


def count(rounds: int) -> dict:
    """Launches, host reads (one chunk and CPU chunks) and ``rounds`` CPU times per problem."""
    from vadgs.mvs import PatchMatchConfig, patchmatch

    counter = _load("_launch_count", REPO / "tests" / "launch_count.py").LaunchCounter
    out = {}
    for name, prob in COUNT_PROBLEMS.items():
        args, kw, _ = _synthetic(*prob)
        row = {}
        for key, chunk in (("one_chunk", ONE_CHUNK), ("cpu_chunks", None)):
            with counter() as c:
                patchmatch(*args, PatchMatchConfig(chunk_size=chunk), **kw)
            row[key] = (c.launches, c.host_reads)
        configs = {"seconds": PatchMatchConfig()}
        if "joint_scoring" in {f.name for f in dataclasses.fields(PatchMatchConfig)}:
            configs["joint_seconds"] = PatchMatchConfig(joint_scoring=True)
            with counter() as c:
                patchmatch(*args, PatchMatchConfig(chunk_size=ONE_CHUNK, joint_scoring=True), **kw)
            row["joint"] = c.launches
        times: dict = {key: [] for key in configs}
        for cfg in configs.values() if rounds else ():
            patchmatch(*args, cfg, **kw)  # warm-up
        for _ in range(rounds):  # interleaved: the machine's load moves
            for key, cfg in configs.items():
                t = time.perf_counter()
                patchmatch(*args, cfg, **kw)
                times[key].append(time.perf_counter() - t)
        row.update(times)
        out[name] = row
    return out


def _street_problems():
    if not STREET_A.is_dir():
        return {}
    st = _load("_mvs_street", REPO / "examples" / "mvs_street.py")
    from vadgs.geometry import cameras_in_object_frame

    sc = st.StreetScene(STREET_A)
    b = st.batch(sc, [20])
    args = (b["img"], b["simg"], b["K"], b["sK"], b["w2c"], b["sw2c"], st.DEPTH_RANGE)
    probs = {"street_a frame 20 (480x288, 4 sources)": (args, {}, b["depth"], st.CONFIG)}
    frame = 12
    track = st.largest_moving_car(sc, frame)
    b = st.batch(sc, [frame])
    frames = [frame, *st.source_frames(frame)]
    obj = torch.stack([sc.object_to_world(track, f) for f in frames])
    w2c = cameras_in_object_frame(torch.cat([b["w2c"], b["sw2c"][0]]), obj)
    mask = b["inst"][:, None] == track
    kw = dict(mask=mask, src_masks=(b["sinst"] == track)[:, :, None])
    args = (b["img"], b["simg"], b["K"], b["sK"], w2c[:1], w2c[None, 1:], st.DEPTH_RANGE)
    gt = torch.where(mask, b["depth"], torch.zeros_like(b["depth"]))
    probs[f"street_a frame {frame}, moving car {track} (object frame, regions)"] = (args, kw, gt, st.CONFIG)
    return probs


def results(path: str, seed: int = 0) -> None:
    """Run the comparison problems with this tree's vadgs (``seed``) and save the results to ``path``."""
    from vadgs.mvs import PatchMatchConfig, patchmatch

    probs = {}
    for name, fronto in (("plane (fronto, test scene)", True), ("plane (slanted, test scene)", False)):
        sc = _plane_scene() if fronto else _plane_scene(normal=(0.35, -0.25, -1.0), z0=2.0, seed=1)
        args = (sc.image, sc.src_images, sc.K, sc.src_K, sc.world_to_cam, sc.src_world_to_cam, (1.0, 10.0))
        probs[name] = (args, {}, sc.depth, PatchMatchConfig())
    args, kw, gt = _synthetic(2, 4, (80, 112), True)
    probs["plane B=2 V=4 80x112 +regions,init"] = (args, kw, gt, PatchMatchConfig())
    probs.update(_street_problems())
    out = {}
    for name, (args, kw, gt, cfg) in probs.items():
        t = time.perf_counter()
        res = patchmatch(*args, dataclasses.replace(cfg, seed=seed), **kw)
        out[name] = dict(depth=res.depth, raw=res.raw_depth, mask=res.mask, gt=gt, s=time.perf_counter() - t)
    torch.save(out, path)


def joint_accuracy(seeds: tuple[int, ...] = (0, 1, 2)) -> None:
    """The default against ``joint_scoring`` on street_a frame 20: raw depths within 1 % / 5 % of truth."""
    from vadgs.mvs import patchmatch

    probs = _street_problems()
    if not probs:
        raise SystemExit(f"joint: needs {STREET_A}")
    args, kw, gt, cfg = probs["street_a frame 20 (480x288, 4 sources)"]
    known = gt > 0
    for joint in (False, True):
        row = []
        for seed in seeds:
            d = patchmatch(*args, dataclasses.replace(cfg, seed=seed, joint_scoring=joint), **kw).raw_depth
            rel = (d - gt).abs() / gt.clamp_min(1e-6)
            row.append([float(((rel <= t) & (d > 0) & known).sum() / known.sum()) for t in (0.01, 0.05)])
        cells = ", ".join(f"seed {s}: {100 * a:.1f} / {100 * b:.1f} %" for s, (a, b) in zip(seeds, row))
        mean = [100 * sum(r[i] for r in row) / len(row) for i in (0, 1)]
        print(f"joint_scoring={joint}: within 1 / 5 % {cells}; mean {mean[0]:.1f} / {mean[1]:.1f} %")


def _accuracy(depth: torch.Tensor, gt: torch.Tensor) -> tuple[float, float]:
    known = gt > 0
    rel = (depth - gt).abs() / gt.clamp_min(1e-6)
    n = max(int(known.sum()), 1)
    return float(((rel <= 0.01) & (depth > 0) & known).sum()) / n, float(((depth > 0) & known).sum()) / n


def _in_tree(tree: str, *argv: str) -> str:
    env = dict(os.environ, PYTHONPATH=str(Path(tree).resolve()))
    cmd = [sys.executable, str(Path(__file__).resolve()), *argv]
    return subprocess.run(cmd, env=env, check=True, capture_output=True, text=True).stdout


def main() -> None:
    """Command line."""
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("what", choices=["count", "compare", "joint", "_count_json", "_results"])
    ap.add_argument("--old", help="a tree whose vadgs to run the same problems with (subprocess)")
    ap.add_argument("--rounds", type=int, default=5, help="timed calls per problem (after a warm-up)")
    ap.add_argument("--out", help=argparse.SUPPRESS)
    ap.add_argument("--seed", type=int, default=0, help=argparse.SUPPRESS)
    args = ap.parse_args()
    torch.set_num_threads(1)
    import vadgs

    if args.what == "_count_json":
        print(json.dumps(count(args.rounds)))
        return
    if args.what == "_results":
        results(args.out, args.seed)
        return
    if args.what == "joint":
        joint_accuracy()
        return
    if args.what == "count":
        new = json.loads(_in_tree(REPO, "_count_json", "--rounds", "0"))
        old = json.loads(_in_tree(args.old, "_count_json", "--rounds", "0")) if args.old else None
        for _ in range(2):  # timing phases alternate between the trees: the machine's load moves
            for rows, tree in ((old, args.old), (new, REPO)):
                if rows is None:
                    continue
                timed = json.loads(_in_tree(tree, "_count_json", "--rounds", str(args.rounds)))
                for name, row in rows.items():
                    for key in ("seconds", "joint_seconds"):
                        if key in timed[name]:
                            row[key] = row.get(key, []) + timed[name][key]
        for rows in (new, old):
            for row in rows.values() if rows else ():
                for key in ("seconds", "joint_seconds"):
                    if key in row:
                        row[key] = statistics.median(row[key]) if row[key] else float("nan")  # --rounds 0
        print(f"new: {REPO}; old: {args.old}")
        head = "launches (one chunk) | host reads | launches (CPU chunks) | CPU ms (median)"
        print(f"| problem | {head} | joint_scoring: launches, CPU ms |")
        print("|---|---|---|---|---|---|")
        for name, row in new.items():
            o = old[name] if old else None

            def cell(key, i, o=o, row=row):
                return f"{o[key][i]:,} → {row[key][i]:,}" if o else f"{row[key][i]:,}"

            ms = (
                f"{o['seconds'] * 1e3:.0f} → {row['seconds'] * 1e3:.0f}"
                if o
                else f"{row['seconds'] * 1e3:.0f}"
            )
            joint = f"{row['joint']:,}, {row['joint_seconds'] * 1e3:.0f}" if "joint" in row else "–"
            print(
                f"| {name} | {cell('one_chunk', 0)} | {cell('one_chunk', 1)} | {cell('cpu_chunks', 0)} "
                f"| {ms} | {joint} |"
            )
        return
    if not args.old:
        raise SystemExit("compare: --old TREE is required")
    with tempfile.TemporaryDirectory() as tmp:
        _in_tree(args.old, "_results", "--out", f"{tmp}/old.pt")
        _in_tree(args.old, "_results", "--out", f"{tmp}/old1.pt", "--seed", "1")
        results(f"{tmp}/new.pt")
        old, new = torch.load(f"{tmp}/old.pt"), torch.load(f"{tmp}/new.pt")
        old1 = torch.load(f"{tmp}/old1.pt")
    print(f"old: {args.old}; new: {Path(vadgs.__file__).parent}")
    print("new vs old (seed 0), and in brackets old seed 1 vs old seed 0: the spread of the search itself")
    head = "both valid: depth within 1e-3 / 1e-2 rel. | masks agree | GT within 1 % old → new"
    print(f"| problem | {head} | completeness old → new | s old → new |")
    print("|---|---|---|---|---|---|")

    def agreement(a, b):
        both = a["mask"] & b["mask"]
        rel = (b["raw"] - a["raw"]).abs() / a["raw"]
        nb = max(int(both.sum()), 1)
        close = [float((rel[both] <= tol).sum()) / nb for tol in (1e-3, 1e-2)]
        return close, float((a["mask"] == b["mask"]).float().mean())

    for name in new:
        o, n = old[name], new[name]
        (c3, c2), agree = agreement(o, n)
        (s3, s2), s_agree = agreement(o, old1[name])
        (ao, co), (an, cn) = _accuracy(o["depth"], o["gt"]), _accuracy(n["depth"], n["gt"])
        cells = [f"{c3:.3f} / {c2:.3f} ({s3:.3f} / {s2:.3f})", f"{agree:.3f} ({s_agree:.3f})"]
        cells += [f"{ao:.3f} → {an:.3f}", f"{co:.3f} → {cn:.3f}", f"{o['s']:.1f} → {n['s']:.1f}"]
        print(f"| {name} | {' | '.join(cells)} |")


if __name__ == "__main__":
    main()
