"""VAD-GS against the baseline trainer and the paper's ablations, on one scene.

Trains each variant with the same seed, iterations and trainer config, then evaluates on the
test split (PSNR, PSNR*, SSIM, #G, depth AbsRel and δ < 1.05 overall, on the traffic sign, on its
part no LiDAR point came near (the board) and on facades above 5 m) and measures the sign's
completeness: the share of its ground-truth surface (sampled from ``gt/static.ply``) within
10 cm of a Gaussian centre. Writes one JSON per variant and a markdown table; prints the table.

Variants: ``baseline`` (standard ADC; identical to the paper's "w/o voxel visibility reasoning",
which disables everything else), ``vadgs``, ``no_view_selection`` (consecutive frames),
``no_geometric_losses``.

Run (from the repository root; ../shared present):

    python benchmarks/vad_ablation.py ../shared/data/street_a --config benchmarks/street_config.json \
        --out runs/ablation_street_a --variants baseline vadgs no_view_selection no_geometric_losses
"""

from __future__ import annotations

import argparse
import dataclasses
import json
from pathlib import Path

import numpy as np
import torch
import trimesh
from scipy.spatial import cKDTree

from vadgs.data import load_scene
from vadgs.geometry import backproject_depth
from vadgs.mvs import PlanarCompletionConfig
from vadgs.train.config import TrainConfig
from vadgs.train.results.evaluate import evaluate, render_test_view
from vadgs.train.trainer import Trainer
from vadgs.train.vad import ReconstructConfig, VisibilityDensifyConfig

VARIANTS = {
    "baseline": None,
    "vadgs": VisibilityDensifyConfig(),
    "no_view_selection": VisibilityDensifyConfig(view_selection=False),
    "no_geometric_losses": VisibilityDensifyConfig(geometric_losses=False),
    # strategy variants (not paper ablations): redo instances still flagged, planar completion,
    # finer matching of small instances
    "cooldown0": VisibilityDensifyConfig(cooldown_events=0),
    "cooldown1": VisibilityDensifyConfig(cooldown_events=1),
    "references3": VisibilityDensifyConfig(references=3),
    "references4": VisibilityDensifyConfig(references=4),
    "cooldown0_4096": VisibilityDensifyConfig(
        cooldown_events=0, reconstruct=ReconstructConfig(max_match_pixels=4096)
    ),
    "planar_cooldown0": VisibilityDensifyConfig(
        cooldown_events=0, reconstruct=ReconstructConfig(planar=PlanarCompletionConfig())
    ),
    "no_planar": VisibilityDensifyConfig(reconstruct=ReconstructConfig(planar=None)),
    # the events' budget: today a count of PatchMatch work (work_budget, deterministic); until
    # round 17 a fraction of the wall-clock training time so far (0.1, then 0.2), kept as variants
    "budget0.1": VisibilityDensifyConfig(work_budget=None, time_budget=0.1),
    "budget0.2": VisibilityDensifyConfig(work_budget=None, time_budget=0.2),
    "no_budget": VisibilityDensifyConfig(work_budget=None, time_budget=None),
    "no_upsample": VisibilityDensifyConfig(reconstruct=ReconstructConfig(max_upsample=1)),
    "no_upsample_no_planar": VisibilityDensifyConfig(
        reconstruct=ReconstructConfig(max_upsample=1, planar=None)
    ),
    # fewer, wider Gaussians per reconstructed surface (issue 21: the model's size and its step time)
    "thin2": VisibilityDensifyConfig(reconstruct=ReconstructConfig(thin_factor=2.0)),
    "thin3": VisibilityDensifyConfig(reconstruct=ReconstructConfig(thin_factor=3.0)),
    "thin1.5": VisibilityDensifyConfig(reconstruct=ReconstructConfig(thin_factor=1.5)),
    # the MVS priors everywhere, as the paper (the default keeps them beyond the voxels only, since
    # round 33: a real log's MVS depth at the LiDAR's edges, issue 47)
    "mvs_prior_everywhere": VisibilityDensifyConfig(mvs_prior_beyond_voxels=False),
}


def sign_surface(scene, samples: int = 20000) -> np.ndarray | None:
    """``(samples, 3)`` points on the signs' true surface (``gt/static.ply``), seeded; None without."""
    root = scene.root
    mesh_path, face_path = root / "gt" / "static.ply", root / "gt" / "static_face_instance.npy"
    signs = scene.instance_ids("sign")
    if not (mesh_path.is_file() and face_path.is_file() and signs):
        return None
    mesh = trimesh.load(mesh_path, process=False)
    faces = np.isin(np.load(face_path), signs)
    sub = mesh.submesh([np.nonzero(faces)[0]], append=True)
    return np.asarray(trimesh.sample.sample_surface(sub, samples, seed=0)[0], dtype=np.float32)


def surface_completeness(centres: np.ndarray, surface: np.ndarray, radius: float = 0.1) -> dict[str, float]:
    """Share of ``surface`` samples (and of the board's, above 4.5 m) within ``radius`` of a centre."""
    # nearest centre of every sample by a k-d tree (a dense cdist would need samples x centres floats)
    d = cKDTree(centres).query(surface, k=1)[0]
    board = surface[:, 2] > 4.5
    return {
        "sign": float((d < radius).mean()),
        "sign_board": float((d[board] < radius).mean()) if board.any() else float("nan"),
    }


def sign_completeness(model, scene, radius: float = 0.1, samples: int = 20000) -> dict[str, float]:
    """Share of the sign's true surface (and its board above 4.5 m) within ``radius`` of a centre."""
    surface = sign_surface(scene, samples)
    if surface is None:
        return {}
    g = model.gaussians_at(0)
    centres = g.means.detach()[model.node_ids[g.ids] == -1].numpy()  # static Gaussians
    return surface_completeness(centres, surface, radius)


def sign_lidar_depth(model, scene, raster, radius: float = 0.25) -> dict[str, dict[str, float]]:
    """Depth AbsRel / δ<1.05 on the sign's pixels whose true surface LiDAR missed, and the rest.

    A test pixel of a ``sign`` instance is "missed" when its ground-truth 3D point is farther than
    ``radius`` from every LiDAR point of the scene (all frames); "seen" are the others. Each part
    also reports the height range (world z, m) of its pixels' true points: on street_a the missed
    part is the board, above the LiDAR's reach, and the seen part the pole's lower part. Returns
    ``{"sign_lidar_missed": {...}, "sign_lidar_seen": {...}}`` (a key is absent without pixels).
    """
    signs = scene.instance_ids("sign")
    if not signs:
        return {}
    lidar = torch.cat([scene.lidar(f.index).points for f in scene.frames]).numpy()
    tree = cKDTree(lidar)
    rel: dict[bool, list[torch.Tensor]] = {True: [], False: []}
    for v in scene.test_views:
        ins = scene.load_instances([v])[0]
        gtd = scene.load_depths([v])
        m = torch.isin(ins, torch.tensor(signs)) & (gtd[0, 0] > 0)
        if not m.any():
            continue
        cams = scene.cameras([v])
        pts = backproject_depth(gtd, cams.K, cams.cam_to_world)[0][:, m].T
        missed = torch.from_numpy(tree.query(pts.numpy())[0] > radius)
        d = render_test_view(model, scene, v, raster).raster.depth[0, 0][m]
        g = gtd[0, 0][m]
        r = torch.stack([(d - g).abs() / g, torch.maximum(d / g, g / d.clamp(min=1e-6)), pts[:, 2]])
        for key in (True, False):
            rel[key].append(r[:, missed == key])
    out = {}
    for key, name in ((True, "sign_lidar_missed"), (False, "sign_lidar_seen")):
        r = torch.cat(rel[key], 1) if rel[key] else torch.zeros(3, 0)
        if r.shape[1]:
            out[name] = {
                "absrel": float(r[0].mean()),
                "delta_1.05": float((r[1] < 1.05).float().mean()),
                "pixels": int(r.shape[1]),
                "height_m": [round(float(r[2].min()), 2), round(float(r[2].max()), 2)],
            }
    return out


def run_variant(scene, name: str, config: TrainConfig, out: Path) -> dict:
    """Train and evaluate one variant; returns its metrics."""
    vad = VARIANTS[name]
    config = dataclasses.replace(config, vad=vad)  # the strategy is part of the run's config
    ckpt = out / name / "checkpoint.pt"
    if ckpt.is_file():  # finished or interrupted earlier: continue (or just evaluate)
        trainer = Trainer.from_checkpoint(ckpt, scene=scene, progress=False)
        if trainer.config.to_dict() != config.to_dict():
            raise ValueError(f"{ckpt}: trained with another config; remove it or use another --out")
    else:
        trainer = Trainer(scene, config, out_dir=out / name, progress=False)
    result = trainer.train()
    train_s = trainer.train_s
    metrics = evaluate(trainer.model, scene, with_lpips=False).to_dict()
    metrics.pop("per_view", None)
    metrics["completeness"] = sign_completeness(trainer.model, scene)
    metrics["depth"].update(sign_lidar_depth(trainer.model, scene, config.raster))
    metrics["train_s"] = train_s
    metrics["steps"] = result.step
    if vad is not None:
        events = trainer.state.get("vad_events", [])
        metrics["vad_events"] = [{k: v for k, v in e.items()} for e in events]
        metrics["vad_s"] = sum(e["total_s"] for e in events)
        metrics["vad_share"] = metrics["vad_s"] / max(train_s, 1e-9)
    (out / f"{name}.json").write_text(json.dumps(metrics, indent=1, default=str))
    return metrics


def _fmt(x, p=3):
    return "–" if x is None or (isinstance(x, float) and x != x) else f"{x:.{p}f}"


def table(results: dict[str, dict]) -> str:
    """Markdown table of the variants."""
    head = (
        "| variant | PSNR | PSNR* | SSIM | #G | AbsRel all | δ<1.05 all | AbsRel sign | δ<1.05 sign "
        "| AbsRel sign, LiDAR-missed | δ<1.05 sign, LiDAR-missed "
        "| AbsRel facade>5m | δ<1.05 facade>5m | sign compl. | board compl. | train s | VAD s (share) |"
    )
    rows = [head, "|" + "---|" * 17]
    for name, m in results.items():
        dep = m.get("depth", {})
        c = m.get("completeness", {})
        cells = [
            name,
            _fmt(m["psnr"], 2),
            _fmt(m["psnr_star"], 2),
            _fmt(m["ssim"]),
            str(m["num_gaussians"]),
            *(
                _fmt(dep.get(region, {}).get(key))
                for region in ("all", "sign", "sign_lidar_missed", "upper_facade")
                for key in ("absrel", "delta_1.05")
            ),
            _fmt(c.get("sign")),
            _fmt(c.get("sign_board")),
            f"{m['train_s']:.0f}",
            f"{_fmt(m.get('vad_s'), 0)} ({_fmt(m.get('vad_share'), 2)})",
        ]
        rows.append("| " + " | ".join(cells) + " |")
    return "\n".join(rows)


def main() -> None:
    """Command line."""
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("scene")
    ap.add_argument("--config", help="TrainConfig JSON (same for every variant)")
    ap.add_argument("--scale", type=float, default=0.5)
    ap.add_argument("--out", default="runs/ablation")
    paper = ["baseline", "vadgs", "no_view_selection", "no_geometric_losses"]
    ap.add_argument("--variants", nargs="+", default=paper, choices=list(VARIANTS))
    ap.add_argument("--threads", type=int, default=1)
    # the compositor's chunk schedule (vadgs.render.composite._chunk_size), for control runs
    ap.add_argument("--chunk-growth", type=int, help="at most this many times chunk_size (1: fixed chunks)")
    ap.add_argument("--step-slots", type=int, help="grow the chunk below this many tile x Gaussian slots")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    import vadgs.render.composite as composite

    if args.chunk_growth is not None:
        composite._MAX_CHUNK_GROWTH = args.chunk_growth
    if args.step_slots is not None:
        composite._STEP_SLOTS = args.step_slots
    scene = load_scene(args.scene, scale=args.scale)
    config = (
        TrainConfig.from_dict(json.loads(Path(args.config).read_text())) if args.config else TrainConfig()
    )
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    results = {}
    for name in args.variants:
        results[name] = run_variant(scene, name, config, out)
        print(f"{name}: done", flush=True)
    md = table(results)
    (out / "table.md").write_text(md + "\n")
    print(md)


if __name__ == "__main__":
    main()
