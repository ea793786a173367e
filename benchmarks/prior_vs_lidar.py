"""The geometric losses' depth prior of each training view against the view's own LiDAR sweep.

VAD-GS's prior where no MVS depth exists is the voxel depth of the pixel's own instance; for a
moving object, its grid posed at the view's time. Prints, on the tracks' pixels and on the rest,
how much of the prior lies more than 10 % off the sweep, then by track. ``--tracks-only`` then
rasterises the tracks' grids alone three ways, to tell where a track's prior leaves its sweep:
every voxel of the grid (its points from every frame, gathered with each frame's cuboid), only the
voxels the view's own sweep observed, and those with the track's mask eroded by 1 and 2 pixels
(its silhouette). Used for issue 47 on PandaSet 002 (docs/results.md, "A real log")::

    OMP_NUM_THREADS=1 python benchmarks/prior_vs_lidar.py scenes/ps002 RUN/checkpoint.pt --scale 0.5
    OMP_NUM_THREADS=1 python benchmarks/prior_vs_lidar.py scenes/ps002 RUN/checkpoint.pt --tracks-only
    OMP_NUM_THREADS=1 python benchmarks/prior_vs_lidar.py scenes/ps002 RUN/checkpoint.pt --per-view 8
    OMP_NUM_THREADS=1 python benchmarks/prior_vs_lidar.py scenes/ps002 RUN/checkpoint.pt --in-front

``--reach`` splits the MVS prior pixels by what the view's voxel z-buffer has on their ray (a
voxel of the pixel's own instance, another's only, none: beyond the LiDAR's reach) and gives each
part's accuracy against the view's sweep; the split ``mvs_prior_beyond_voxels`` makes (on by
default: the events keep the last part only, so this reads a run trained with
``--vad.no-mvs-prior-beyond-voxels``, the paper's priors everywhere)::

    OMP_NUM_THREADS=1 python benchmarks/prior_vs_lidar.py scenes/ps002-36 RUN/checkpoint.pt --reach

``--in-front`` tells, of the static prior pixels more than 10 % in front of the view's own sweep,
how many the LiDAR check could see (a voxel of the view's own sweep nearest there:
``VisibilityIndex.observed_depth``) and where the whole scan's voxel z-buffer puts the surface
against the prior: within 10 %, nearer, farther, or none.
"""

from __future__ import annotations

import argparse
import warnings
from collections import defaultdict
from dataclasses import replace

import torch
import torch.nn.functional as F

from vadgs.data import load_scene
from vadgs.data.lidar import lidar_depth_map
from vadgs.geometry import Cameras
from vadgs.geometry.zbuffer import rasterize_voxels
from vadgs.train.trainer import Trainer
from vadgs.train.vad.priors import state_priors


def track_depth(index, view: int, observed: bool) -> tuple[torch.Tensor, torch.Tensor]:
    """The nearest track voxel surface ``(H, W)`` and its track id (0: none) of one view."""
    depth = torch.zeros_like(index.voxel_raster(view)[0][0])
    label = torch.zeros(depth.shape, dtype=torch.long, device=depth.device)
    fpos, cams = index.inputs.frame_position(view), index.camera(view)
    config = replace(index.zbuffer, only_observed=observed)
    for tid, grid in index.track_grids.items():
        track = index.inputs.tracks[tid]
        if not bool(track.valid[fpos]):
            continue
        o2w = track.object_to_world[fpos].to(cams.world_to_cam)
        obj = Cameras(cams.K, cams.world_to_cam @ o2w[None], cams.image_size)
        d = index.pad(rasterize_voxels(grid, obj, [view], config).depth[0])[0]
        closer = (d > 0) & ((depth == 0) | (d < depth))
        depth, label = torch.where(closer, d, depth), torch.where(closer, tid, label)
    return depth, label


def tracks_only(scene, index) -> None:
    """Print the tracks' prior against the sweeps: every voxel, observed voxels, eroded masks."""
    variants = (("every voxel", False, 0), ("observed voxels", True, 0))
    variants += (("observed, eroded 1 px", True, 1), ("observed, eroded 2 px", True, 2))
    for name, observed, erode in variants:
        n = front = behind = 0
        for v in scene.train_views:
            sweep = lidar_depth_map(scene, v)[0, 0]
            h, w = sweep.shape
            d, label = track_depth(index, v, observed)
            d, label = d[:h, :w], label[:h, :w]
            own = ((label > 0) & (label == index.instances(v)[:h, :w])).float()[None, None]
            if erode:
                own = -F.max_pool2d(-own, 2 * erode + 1, 1, erode)
            m = (own[0, 0] > 0.5) & (d > 0) & (sweep > 0)
            rel = (d[m] - sweep[m]) / sweep[m]
            n += int(m.sum())
            front += int((rel < -0.1).sum())
            behind += int((rel > 0.1).sum())
        print(
            f"{name}: {n} pixels with a prior and a return, {100 * front / max(n, 1):.1f} % in front "
            f"by > 10 %, {100 * behind / max(n, 1):.1f} % behind"
        )


def in_front(scene, tr, index) -> None:
    """Print what the voxels say where a static prior lies > 10 % in front of the view's sweep."""
    tracks = torch.tensor(sorted(scene.tracks), dtype=torch.long)
    counts = dict(in_front=0, checked=0, scan_agrees=0, scan_nearer=0, scan_farther=0, scan_none=0)
    for v in scene.train_views:
        targets = tr.strategy.geometry_targets(tr.state, v)
        if targets is None or targets.depth is None:
            continue
        prior = targets.depth[0, 0].cpu()
        h, w = prior.shape
        sweep = lidar_depth_map(scene, v)[0, 0]
        static = ~torch.isin(index.instances(v)[:h, :w].cpu(), tracks)
        m = (prior > 0) & (sweep > 0) & (prior < 0.9 * sweep) & static
        scan = index.voxel_depth(v)[0][0, :h, :w].cpu()[m]
        rel = (prior[m] - scan) / scan.clamp_min(1e-6)
        counts["in_front"] += int(m.sum())
        counts["checked"] += int((index.observed_depth(v)[0, :h, :w].cpu()[m] > 0).sum())
        counts["scan_none"] += int((scan == 0).sum())
        counts["scan_agrees"] += int(((scan > 0) & (rel.abs() <= 0.1)).sum())
        counts["scan_nearer"] += int(((scan > 0) & (rel > 0.1)).sum())
        counts["scan_farther"] += int(((scan > 0) & (rel < -0.1)).sum())
    print(
        f"static prior pixels > 10 % in front of the view's sweep: {counts['in_front']}; the check sees "
        f"{counts['checked']} of them; the scan's voxel z-buffer there: within 10 % of the prior "
        f"{counts['scan_agrees']}, nearer {counts['scan_nearer']}, farther {counts['scan_farther']}, "
        f"none {counts['scan_none']}"
    )


def _tally(acc: list[float], rel: torch.Tensor) -> None:
    """Add to ``acc``'s last three: the pixels with a return, those > 10 % off, their sum of AbsRel."""
    acc[-3] += rel.numel()
    acc[-2] += int((rel > 0.1).sum())
    acc[-1] += float(rel.sum())


def reach(scene, tr, index) -> None:
    """Print the MVS priors split by the voxel z-buffer on their ray, with their accuracy."""
    priors = state_priors(tr.state)  # the MVS priors as the events kept them (merge_priors)
    tracks = torch.tensor(sorted(scene.tracks), dtype=torch.long)
    parts: dict[tuple[str, str], list[float]] = defaultdict(
        lambda: [0, 0, 0, 0.0]
    )  # px, returns, off, AbsRel
    for v in scene.train_views:
        if v not in priors:
            continue
        h, w = index.size(v)
        prior = priors[v][0][0, :h, :w].cpu()
        sweep = lidar_depth_map(scene, v)[0, 0]
        vox = index.voxel_depth(v)[0][0, :h, :w].cpu()
        own = index.own_voxel_depth(v)[0, :h, :w].cpu()
        track = torch.isin(index.instances(v)[:h, :w].cpu(), tracks)
        has = prior > 0
        where = {
            "own instance's voxel": has & (own > 0),
            "another's voxel only": has & (vox > 0) & (own == 0),
        }
        where["no voxel (beyond)"] = has & (vox == 0)
        for name, m in where.items():
            for kind, k in (("static", ~track), ("track", track)):
                mm = m & k
                on = mm & (sweep > 0)
                parts[(name, kind)][0] += int(mm.sum())
                _tally(parts[(name, kind)], ((prior[on] - sweep[on]) / sweep[on]).abs())
    total = sum(p[0] for p in parts.values())
    print(f"{len(priors)} views with MVS priors, {total} prior pixels")
    for (name, kind), (n, on, off, rel) in parts.items():
        print(
            f"{name:22s} {kind:6s}: {n:7d} px ({100 * n / max(total, 1):5.1f} %); on a return {on:6d}: "
            f"{100 * off / max(on, 1):5.1f} % off by > 10 %, AbsRel {rel / max(on, 1):.3f}"
        )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("scene")
    ap.add_argument("checkpoint", help="a VAD-GS run's checkpoint")
    ap.add_argument("--scale", type=float, default=0.5)
    ap.add_argument("--tracks-only", action="store_true", help="the tracks' grids alone, three ways")
    ap.add_argument("--per-view", type=int, default=0, help="then the N views with most checked pixels")
    ap.add_argument("--in-front", action="store_true", help="the static priors in front of the sweep")
    ap.add_argument("--reach", action="store_true", help="the MVS priors by the voxels on their ray")
    args = ap.parse_args()
    torch.set_num_threads(1)
    warnings.simplefilter("ignore")
    scene = load_scene(args.scene, scale=args.scale)
    tr = Trainer.from_checkpoint(args.checkpoint, scene, out_dir=None, progress=False)
    index = tr.strategy.prepare()
    if args.tracks_only:
        tracks_only(scene, index)
        return
    if args.in_front:
        in_front(scene, tr, index)
        return
    if args.reach:
        reach(scene, tr, index)
        return
    tracks = torch.tensor(sorted(scene.tracks), dtype=torch.long)
    groups: dict[str, list[float]] = defaultdict(lambda: [0, 0, 0.0])  # pixels, > 10 % off, sum AbsRel
    per_track: dict[int, list[int]] = defaultdict(lambda: [0, 0])
    views: list[tuple[int, int, int, int, int, float]] = []  # view, prior, on a return, front, behind, depth
    for v in scene.train_views:
        targets = tr.strategy.geometry_targets(tr.state, v)
        if targets is None or targets.depth is None:
            continue
        prior = targets.depth[0, 0].cpu()
        sweep = lidar_depth_map(scene, v)[0, 0]
        inst = index.instances(v)[: prior.shape[0], : prior.shape[1]].cpu()
        both = (prior > 0) & (sweep > 0)
        rel = (prior - sweep).abs() / sweep.clamp_min(1e-6)
        signed = (prior[both] - sweep[both]) / sweep[both]
        has = prior > 0
        views.append(
            (v, int(has.sum()), int(both.sum()), int((signed < -0.1).sum()), int((signed > 0.1).sum()),
             float(prior[has].median()) if bool(has.any()) else 0.0)
        )  # fmt: skip
        moving = torch.isin(inst, tracks)
        for name, m in (("tracks", both & moving), ("the rest", both & ~moving)):
            _tally(groups[name], rel[m])
        for t in inst[both & moving].unique().tolist():
            m = both & (inst == t)
            per_track[t][0] += int(m.sum())
            per_track[t][1] += int((rel[m] > 0.1).sum())
    for name, (n, off, total) in groups.items():
        print(
            f"{name}: {int(n)} pixels with a prior and a return, "
            f"{100 * off / max(n, 1):.1f} % off by > 10 %, mean AbsRel {total / max(n, 1):.3f}"
        )
    tot = [sum(row[i] for row in views) for i in range(1, 5)]
    print(
        f"all: {len(views)} views with a prior, {tot[0]} prior pixels, {tot[1]} on a return of the view's "
        f"sweep: {100 * tot[2] / max(tot[1], 1):.1f} % in front by > 10 %, "
        f"{100 * tot[3] / max(tot[1], 1):.1f} % behind"
    )
    for v, n, on, front, behind, depth in sorted(views, key=lambda r: -r[2])[: args.per_view]:
        print(
            f"  {scene.views[v].camera} f{scene.views[v].frame}: {n} prior pixels at {depth:.1f} m (median), "
            f"{on} on a return: {front} in front, {behind} behind by > 10 %"
        )
    for t, (n, off) in sorted(per_track.items(), key=lambda x: -x[1][0])[:10]:
        print(
            f"  track {t} ({scene.tracks[t].class_name}): {n} pixels, "
            f"{100 * off / max(n, 1):.1f} % off by > 10 %"
        )


if __name__ == "__main__":
    main()
