"""How the first VAD-GS event of a scene ends, instance by instance, with and without a setting.

Trains one sampling cycle of ``SCENE`` (every training view once, VAD-GS attached, no work budget),
copies the trainer, and runs the event on both copies: the ``ReconstructConfig`` as it is and with
``--off`` (a boolean field) set to False. Prints each event's flagged / attempted / repaired
instances, the Gaussians added and its ``outcomes`` (the (instance, reference) reconstructions by
reason). Used for issue 47 on a converted PandaSet log (docs/results.md, "A real log")::

    vadgs convert pandaset /data/pandaset/002 --frames 0:36 \\
        --cameras front_left_camera,front_camera,front_right_camera --scale 0.25 --out scenes/ps002
    OMP_NUM_THREADS=1 python benchmarks/event_outcomes.py scenes/ps002 --scale 0.5 --off seen_supports

``--breakdown`` then tells, for each event, why the (instance, reference) reconstructions that ended
``no_voxels`` (the reference sees none of the instance's voxels) did: the instance's kind (a moving
object's track, a derived static cell, a labelled static instance) and what the reference sees of
its voxels (none at all; in its visibility set; in its voxel z-buffer; inside its frustum but behind
other voxels; outside its frustum), after the pairs by kind and outcome and how far the static points
each outcome added lie from the LiDAR's voxels. ``--cycle PATH`` keeps the trained cycle: a checkpoint written
there after training, and resumed from (exactly: ``Trainer.from_checkpoint``) when it exists.
"""

from __future__ import annotations

import argparse
import copy
import dataclasses
import time
import warnings
from collections import Counter
from pathlib import Path
from typing import Any, NamedTuple

import torch

import vadgs.train.vad.event as event_module
from vadgs.data import load_scene
from vadgs.geometry.camera import project_points
from vadgs.train.config import TrainConfig, scale_schedule
from vadgs.train.trainer import Trainer
from vadgs.train.vad import InstanceReconstruction, VisibilityDensifyConfig


class Pair(NamedTuple):
    """One (instance, reference) reconstruction of an event, as recorded."""

    instance: int
    reference: int
    reason: str
    points: torch.Tensor  # (N, 3) added points (world or object frame)
    views: list[int]  # the group: the reference, then its supports


def _kind(index: Any, inst: int) -> str:
    """``"track car"``, ``"static cell"`` (a derived ground cell) or ``"static <class>"``."""
    cls = index.classes().get(inst, "?")
    if inst in index.inputs.tracks:
        return f"track {cls}"
    return "static cell" if cls == "static" else f"static {cls}"


def _outcome(reason: str) -> str:
    """A reason without its detail, as the event's ``outcomes`` counts it."""
    head = reason.split(": ")[0]
    return head + " (seen)" if head != reason and reason.endswith("(seen)") else head


def why_none(index: Any, inst: int, ref: int) -> dict[str, Any]:
    """What reference ``ref`` sees of instance ``inst``'s voxels, and why that is none.

    Returns ``kind``, ``why`` and the counts it is decided on: ``voxels`` (the instance's: a track's
    whole grid; a static instance's labelled voxels, or those seen through its mask when it has
    fewer than 8), ``visibility`` (those in the reference's visibility set), ``zbuffer`` (those its
    voxel z-buffer shows: for a track, where the track is the nearest surface), ``frustum`` (those
    whose centre projects into its image in front of it), ``views_vis`` / ``views_zbuf`` (training
    views whose visibility set / z-buffer hold any of them), ``depth`` (the median depth of the
    frustum's ones), ``pixels`` (its mask in the reference).
    """
    track = inst if inst in index.inputs.tracks else None
    out: dict[str, Any] = {"kind": _kind(index, inst), "pixels": int((index.instances(ref) == inst).sum())}
    if track is not None:
        if track not in index.track_covis:
            return {**out, "why": "no voxels (no LiDAR point on the track)", "voxels": 0}
        covis = index.track_covis[track]
        voxels = torch.ones(covis.num_voxels, dtype=torch.bool)
    else:
        covis = index.covis
        voxels = index.labels == inst
        if int(voxels.sum()) < 8:
            _, vidx = index.voxel_raster(ref)
            voxels = voxels.clone()
            voxels[torch.unique(vidx[(index.instances(ref) == inst) & (vidx >= 0)])] = True
    ids = torch.nonzero(voxels).flatten()
    out["voxels"] = len(ids)
    if not len(ids):
        return {**out, "why": "no voxels (no LiDAR on it, none seen through its mask)"}
    train = [v for v in index.inputs.train_views]

    def count(seen: torch.Tensor) -> int:
        return int(torch.isin(ids, seen.to(ids)).sum())

    out["visibility"] = count(covis.voxels_of(ref))
    out["zbuffer"] = count(index.seen_voxels(ref, track))
    out["views_vis"] = sum(count(covis.voxels_of(v)) > 0 for v in train if v != ref)
    out["views_zbuf"] = sum(count(index.seen_voxels(v, track)) > 0 for v in train if v != ref)
    h, w = index.size(ref)
    uv, z = project_points(covis.voxel_centers[ids][None].float(), index.cameras.K[ref : ref + 1],
                           covis.world_to_cam[ref : ref + 1].float())  # fmt: skip
    uv, z = uv[0], z[0]
    inside = (z > 0) & (uv[:, 0] >= -0.5) & (uv[:, 0] < w - 0.5) & (uv[:, 1] >= -0.5) & (uv[:, 1] < h - 0.5)
    if track is not None and not bool(index.inputs.tracks[track].valid[index.inputs.frame_position(ref)]):
        inside[:] = False  # no pose at the reference's frame
    out["frustum"] = int(inside.sum())
    out["depth"] = float(z[inside].median()) if bool(inside.any()) else None
    if out["visibility"]:
        out["why"] = "in its visibility set (selection found no support)"
    elif out["zbuffer"]:
        out["why"] = "not in its visibility set, in its z-buffer"
    elif out["frustum"]:
        out["why"] = "in its frustum, behind other voxels"
    else:
        out["why"] = "outside its frustum"
    return out


def _where_points_lie(index: Any, pairs: list[Pair]) -> None:
    """Print how far the static points each outcome added lie from the LiDAR's voxels, by shown voxels.

    For each static (instance, reference) pair that added points: the distance of each point to
    the nearest voxel centre of the static grid (the training frames' LiDAR), relative to its
    depth in the reference; grouped by outcome and by how many of the instance's voxels the
    reference's z-buffer shows (1-2: a far cell, below the selection's ``min_shared``, or more).
    """
    from scipy.spatial import cKDTree

    tree = cKDTree(index.covis.voxel_centers.double().numpy())
    groups: dict[tuple[str, str], list[torch.Tensor]] = {}
    for inst, ref, reason, points, _ in pairs:
        if inst in index.inputs.tracks or not len(points):
            continue
        shown = why_none(index, inst, ref).get("zbuffer", 0)
        w2c = index.cameras.world_to_cam[ref].double()
        depth = points.double() @ w2c[2, :3] + w2c[2, 3]
        dist = torch.from_numpy(tree.query(points.double().numpy())[0])
        key = (_outcome(reason), "1-2 voxels shown" if shown <= 2 else "3+ voxels shown")
        groups.setdefault(key, []).append(torch.stack([dist, dist / depth.clamp_min(1e-6), depth], 1))
    print("  added static points: distance to the nearest LiDAR voxel (median; relative to depth), depth:")
    for (outcome, shown), rows in sorted(groups.items()):
        x = torch.cat(rows)
        med = x.median(0).values.tolist()
        print(
            f"    {outcome:14s} {shown:18s} {len(rows):3d} pairs, {len(x):6d} points: {med[0]:.2f} m "
            f"({100 * med[1]:.1f} % of depth), depth {med[2]:.0f} m"
        )


def _against_held_out_lidar(scene: Any, index: Any, pairs: list[Pair], top: int = 0) -> None:
    """Print where the added static points lie against the test frames' own LiDAR (held out).

    Each point projected into each test view where a LiDAR return lands on its pixel: *in front*
    when its depth is more than 10 % nearer than the return (it would hide the surface the LiDAR
    sees: a wrong addition), *on* within 10 %, *behind* more than 10 % farther (hidden there).
    Grouped as :func:`_where_points_lie`; with ``top``, then the ``top`` pairs with the most
    point-views, each with its reference and supports (camera and frame).
    """
    from vadgs.data.lidar import lidar_depth_map

    views = []
    for v in scene.test_views:
        cams = scene.cameras([v])
        views.append((lidar_depth_map(scene, v)[0, 0], cams.K, cams.world_to_cam))
    groups: dict[tuple[str, str], torch.Tensor] = {}
    rows = []
    for inst, ref, reason, points, group in pairs:
        if inst in index.inputs.tracks or not len(points):
            continue
        shown = why_none(index, inst, ref).get("zbuffer", 0)
        key = (_outcome(reason), "1-2 voxels shown" if shown <= 2 else "3+ voxels shown")
        counts = groups.setdefault(key, torch.zeros(4, dtype=torch.long))
        counts[3] += 1
        pair = torch.zeros(3, dtype=torch.long)
        for lidar, K, w2c in views:
            h, w = lidar.shape
            uv, z = project_points(points[None].float(), K, w2c)
            u, v_ = uv[0, :, 0].round().long(), uv[0, :, 1].round().long()
            ok = (z[0] > 0) & (u >= 0) & (u < w) & (v_ >= 0) & (v_ < h)
            ref_d = lidar[v_[ok], u[ok]]
            hit = ref_d > 0
            rel = (z[0][ok][hit] - ref_d[hit]) / ref_d[hit]
            pair += torch.tensor(
                [int((rel < -0.1).sum()), int((rel.abs() <= 0.1).sum()), int((rel > 0.1).sum())]
            )
        counts[:3] += pair
        names = [f"{scene.views[v].camera.removesuffix('_camera')} f{scene.views[v].frame}" for v in group]
        rows.append((int(pair.sum()), inst, _outcome(reason), len(points), pair.tolist(), names))
    print("  added static points against the test frames' LiDAR (point-views on a return):")
    for (outcome, shown), c in sorted(groups.items()):
        total = max(int(c[:3].sum()), 1)
        front, on, behind = (100 * int(c[i]) / total for i in range(3))
        print(
            f"    {outcome:14s} {shown:18s} {int(c[3]):3d} pairs: {total:7d} point-views, in front "
            f"{front:.1f} %, on {on:.1f} %, behind {behind:.1f} %"
        )
    for total, inst, outcome, n, (front, on, _), names in sorted(rows, reverse=True)[:top]:
        t = max(total, 1)
        print(
            f"    instance {inst} ({outcome}, {n} points): {total} point-views, in front "
            f"{100 * front / t:.0f} %, on {100 * on / t:.0f} %; reference {names[0]}, "
            f"supports {', '.join(names[1:])}"
        )


def _breakdown(index: Any, pairs: list[Pair]) -> None:
    """Print an event's (instance, reference) pairs by kind and outcome; why the ``no_voxels`` saw none."""
    kinds = Counter((_kind(index, i), _outcome(reason)) for i, _, reason, _, _ in pairs)
    print("  (instance, reference) pairs by kind and outcome:")
    for (kind, outcome), n in sorted(kinds.items()):
        print(f"    {kind:22s} {outcome:52s} {n:3d}")
    _where_points_lie(index, pairs)
    rows = [(i, r, why_none(index, i, r)) for i, r, reason, _, _ in pairs if "no_voxels" in reason]
    if not rows:
        print("  no (instance, reference) pair ended no_voxels")
        return
    shown = Counter(d.get("zbuffer", 0) for _, _, d in rows)
    print(f"  {len(rows)} no_voxels pairs ({len({i for i, _, _ in rows})} instances); voxels their"
          f" reference's z-buffer shows: {dict(sorted(shown.items()))}; by kind and why:")  # fmt: skip
    for (kind, why), n in sorted(Counter((d["kind"], d["why"]) for _, _, d in rows).items()):
        sel = [d for _, _, d in rows if (d["kind"], d["why"]) == (kind, why)]
        depth = [d["depth"] for d in sel if d.get("depth") is not None]
        others = sum(d.get("views_vis", 0) + d.get("views_zbuf", 0) > 0 for d in sel)
        print(
            f"    {kind:22s} {why:52s} {n:3d}  (other training views see it: {others}; median depth "
            f"{sorted(depth)[len(depth) // 2] if depth else float('nan'):.1f})"
        )
    for i, r, d in rows:
        facts = ", ".join(f"{k} {v:.1f}" if isinstance(v, float) else f"{k} {v}"
                          for k, v in d.items() if k not in ("kind", "why"))  # fmt: skip
        print(f"    instance {i} ref {r}: {d['kind']}; {d['why']}; {facts}")


def main() -> None:
    """Train one cycle, then run the event with the setting on and off."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scene", help="a scene folder (scene.json)")
    ap.add_argument("--scale", type=float, default=0.5)
    ap.add_argument("--off", default="seen_supports", help="a ReconstructConfig setting: False, or None")
    ap.add_argument("--breakdown", action="store_true", help="why the no_voxels pairs saw none")
    ap.add_argument("--cycle", type=Path, help="checkpoint of the trained cycle: resumed, or written")
    ap.add_argument("--held-out", action="store_true", help="the added points against the test LiDAR")
    ap.add_argument("--pairs", type=int, default=0, help="with --held-out: the N pairs with most points")
    ap.add_argument(
        "--min-angle",
        type=float,
        help="the view selection's least triangulation angle, degrees (default: its own)",
    )
    ap.add_argument("--min-parallax", type=float, help="the view selection's min_parallax, pixels")
    args = ap.parse_args()
    torch.set_num_threads(1)
    warnings.simplefilter("ignore", UserWarning)
    scene = load_scene(args.scene, scale=args.scale)
    n = len(scene.train_views)
    t0 = time.perf_counter()
    if args.cycle is not None and args.cycle.exists():
        on = Trainer.from_checkpoint(args.cycle, scene, out_dir=None, progress=False)
        print(f"{n} training views, resumed at step {on.step} from {args.cycle}", flush=True)
    else:
        vad = VisibilityDensifyConfig(every_cycles=1, work_budget=None)
        cfg = scale_schedule(TrainConfig(iterations=3 * n, checkpoint_every=10**6, vad=vad))
        on = Trainer(scene, cfg, progress=False)
        print(f"{n} training views, {on.model.num_gaussians} Gaussians at the start", flush=True)
        for _ in range(n - 1):
            on.train_step()
        print(f"{n - 1} steps in {time.perf_counter() - t0:.0f} s", flush=True)
        if args.cycle is not None:
            on.save_checkpoint(args.cycle)
    pairs: list[Pair] = []
    # the event plans every (instance, reference) pair, matches them together and finishes each:
    # a pair's reconstruction is its plan when there is nothing to match, else its finish
    plan, finish = event_module.plan_matches, event_module.finish_match

    def planned(index: Any, refs: list[int], inst: int, *a: Any, **k: Any) -> Any:
        out = plan(index, refs, inst, *a, **k)
        for ref, got in zip(refs, out):
            if isinstance(got, InstanceReconstruction):
                pairs.append(Pair(inst, ref, got.reason, got.points.cpu(), list(got.views)))
        return out

    def finished(index: Any, match_plan: Any, *a: Any, **k: Any) -> Any:
        rec = finish(index, match_plan, *a, **k)
        pairs.append(Pair(match_plan.instance, match_plan.ref, rec.reason, rec.points.cpu(), list(rec.views)))
        return rec

    if args.breakdown or args.held_out:
        event_module.plan_matches = planned  # type: ignore[assignment]
        event_module.finish_match = finished  # type: ignore[assignment]
    chosen = {"min_angle": args.min_angle, "min_parallax": args.min_parallax}
    chosen = {k: v for k, v in chosen.items() if v is not None}
    if chosen:
        rec = on.strategy.reconstruct
        on.strategy.reconstruct = dataclasses.replace(
            rec, selection=dataclasses.replace(rec.selection, **chosen)
        )
    print(f"view selection: {on.strategy.reconstruct.selection}", flush=True)
    off = copy.deepcopy(on)
    was = getattr(off.strategy.reconstruct, args.off)
    off_value = False if isinstance(was, bool) else None  # a bool setting, else an optional one
    off.strategy.reconstruct = dataclasses.replace(off.strategy.reconstruct, **{args.off: off_value})
    for name, trainer in ((f"{args.off}={off_value}", off), (f"{args.off}={was}", on)):
        pairs.clear()
        t1 = time.perf_counter()
        trainer.train_step()  # the event's step
        e = trainer.state["vad_events"][-1]
        print(
            f"{name}: {e['flagged_instances']} flagged, {e['attempted']} attempted, {e['repaired']} repaired,"
            f" +{e['added']} Gaussians, {time.perf_counter() - t1:.0f} s\n  outcomes {e['outcomes']}",
            flush=True,
        )
        if args.breakdown:
            _breakdown(trainer.strategy.index, list(pairs))
        if args.held_out:
            _against_held_out_lidar(scene, trainer.strategy.index, list(pairs), args.pairs)


if __name__ == "__main__":
    main()
