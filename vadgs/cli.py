"""The ``vadgs`` command line.

Subcommands are registered in :data:`COMMANDS`; each is a function ``(argparse.Namespace) -> int``
with an ``add_arguments(parser)`` attribute. ``vadgs --help`` lists them.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import json
import math
import os
import sys
import tempfile
import time
import traceback
from collections.abc import Callable
from pathlib import Path

import torch

from vadgs.io import write_json
from vadgs.train.run import finish_run, frame_position, load_run

__all__ = [
    "COMMANDS",
    "batch",
    "check",
    "convert",
    "demo",
    "eval_run",
    "export_run",
    "main",
    "render_run",
    "train",
    "visibility",
]


# ---------------------------------------------------------------------------------------------------
# argument validation


def _int_at_least(minimum: int) -> Callable[[str], int]:
    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected an integer >= {minimum}, got {text!r}") from None
        if value < minimum:
            raise argparse.ArgumentTypeError(f"expected an integer >= {minimum}, got {value}")
        return value

    parse.__name__ = f"integer >= {minimum}"
    return parse


def _finite_float(zero_ok: bool) -> Callable[[str], float]:
    """An argparse type: a finite number > 0 (or >= 0 with ``zero_ok``, where 0 means "off")."""
    want = "a finite number >= 0 (0 = no limit)" if zero_ok else "a positive number"

    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected {want}, got {text!r}") from None
        if not (math.isfinite(value) and (value > 0 or (zero_ok and value == 0))):
            raise argparse.ArgumentTypeError(f"expected {want}, got {text}")
        return value

    parse.__name__ = want
    return parse


_non_negative_float = _finite_float(zero_ok=True)
_positive_float = _finite_float(zero_ok=False)


def _check_out_dir(path: str | Path, flag: str = "--out", create: bool = True) -> Path:
    """Check, before any work, that the output folder ``path`` can be written (and create it).

    Args:
        path: the folder.
        flag: the argument's name, for the message.
        create: create the folder (and parents); when False only check that it could be
            created (its nearest existing ancestor is a writable folder), leaving the disk as it is.

    Raises:
        ValueError: if ``path`` is an existing file, cannot be created, or is not writable; the
            message names ``flag`` and the path.
    """
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise ValueError(f"{flag} {path}: expected a folder, got an existing file")
    if not path.exists() and not create:
        parent = path.parent
        while not parent.exists() and parent != parent.parent:
            parent = parent.parent
        if not parent.is_dir():
            raise ValueError(f"{flag} {path}: cannot create the folder ({parent} is a file)")
        if not os.access(parent, os.W_OK | os.X_OK):
            raise ValueError(f"{flag} {path}: cannot create the folder ({parent} is not writable)")
        return path
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise ValueError(f"{flag} {path}: cannot create the folder ({e.strerror or e})") from None
    try:
        with tempfile.NamedTemporaryFile(dir=path, prefix=".vadgs-write-test-"):
            pass
    except OSError as e:
        raise ValueError(f"{flag} {path}: folder is not writable ({e.strerror or e})") from None
    return path


def _run_dir(run: str | Path) -> Path:
    """The run folder of ``RUN`` given as the folder or as its checkpoint file."""
    run = Path(run)
    return run.parent if run.is_file() else run


def _scene_arg(value: str | None) -> Path:
    from vadgs.data import sample_scene_path

    return Path(value) if value else sample_scene_path()


def visibility(args: argparse.Namespace) -> int:
    """Voxel visibility reasoning on a scene: voxelise LiDAR, z-buffer one view, write a PNG panel."""
    from vadgs.data import load_scene
    from vadgs.data.lidar import accumulate_lidar
    from vadgs.geometry import ZBufferConfig, rasterize_voxels, voxelize
    from vadgs.viz import colorize_depth, colorize_index, image_to_uint8, save_panel

    out = _check_out_dir(args.out)
    scene = load_scene(_scene_arg(args.scene), scale=args.scale)
    t0 = time.perf_counter()
    acc = accumulate_lidar(scene)
    grid = voxelize(acc.points, args.voxel_size, acc.point_views, scene.num_views)
    t1 = time.perf_counter()
    view = args.view if args.view is not None else scene.train_views[len(scene.train_views) // 2]
    raster = rasterize_voxels(
        grid, scene.cameras([view]), [view], ZBufferConfig(only_observed=args.only_observed)
    )
    t2 = time.perf_counter()
    image = scene.load_images([view])[0]
    gt = scene.load_depths([view])[0, 0] if scene.views[view].depth is not None else None
    depth = raster.depth[0, 0]
    panels = [image_to_uint8(image), colorize_depth(depth), colorize_index(raster.index[0])]
    titles = ["image", f"voxel depth ({args.voxel_size} m voxels)", "pixel -> voxel index"]
    metrics = {
        "scene": scene.name,
        "view": view,
        "camera": scene.views[view].camera,
        "frame": scene.views[view].frame,
        "lidar_points": int(acc.points.shape[0]),
        "voxels": len(grid),
        "voxel_view_pairs": int(grid.vis_views.numel()),
        "visible_voxels_in_view": int(raster.visible[0].numel()),
        "voxelize_s": round(t1 - t0, 3),
        "zbuffer_s": round(t2 - t1, 3),
    }
    if gt is not None:
        panels.append(colorize_depth(gt))
        titles.append("ground-truth depth")
        both = (gt > 0) & (depth > 0)
        metrics["gt_pixels_covered"] = round(float(both.sum() / (gt > 0).sum().clamp(min=1)), 4)
        metrics["within_one_voxel"] = round(
            float(((depth - gt).abs()[both] < args.voxel_size).float().mean()) if both.any() else 0.0, 4
        )
    png = save_panel(panels, titles, out / f"visibility_view{view:03d}.png", columns=2)
    write_json(out / "visibility.json", metrics)
    print(json.dumps(metrics, indent=2))
    print(f"wrote {png}")
    return 0


def _visibility_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("scene", nargs="?", help="scene folder (default: the bundled sample)")
    p.add_argument("--out", default="outputs/visibility", help="output folder")
    p.add_argument(
        "--view", type=_int_at_least(0), default=None, help="view index (default: a middle training view)"
    )
    p.add_argument("--voxel-size", type=_positive_float, default=0.2)
    p.add_argument("--scale", type=_positive_float, default=1.0, help="image resolution factor")
    p.add_argument("--only-observed", action="store_true", help="rasterise only voxels observed by the view")


visibility.add_arguments = _visibility_args  # type: ignore[attr-defined]


# ---------------------------------------------------------------------------------------------------
# training


def _deep_update(base: dict, upd: dict, where: str = "config") -> dict:
    for k, v in upd.items():
        if k not in base:
            raise ValueError(f"{where}: unknown key {k!r}")
        if isinstance(base[k], dict) and isinstance(v, dict):
            _deep_update(base[k], v, f"{where}.{k}")
        else:
            base[k] = v
    return base


def _train_config(args: argparse.Namespace) -> object:
    from vadgs.train.config import TrainConfig

    d = TrainConfig().to_dict()
    if args.config:
        _deep_update(d, _read_config_file(args.config))
    vad = _vad_config(args)
    if vad is not None:  # every VAD-GS field, so that --set vad.KEY=... can change any of them
        from vadgs.train.vad import VisibilityDensifyConfig

        full = dataclasses.asdict(VisibilityDensifyConfig())
        d["vad"] = {**_deep_update(full, d.get("vad") or {}, "config.vad"), **vad}
    for item in args.set or []:
        if "=" not in item:
            raise ValueError(f"--set: expected KEY=VALUE, got {item!r}")
        key, value = item.split("=", 1)
        try:
            val = json.loads(value)
        except json.JSONDecodeError:
            val = value
        parts = key.split(".")
        _deep_update(d, _nest(parts, val), "--set")
    for flag, key in (
        ("iterations", "iterations"),
        ("seed", "seed"),
        ("max_minutes", "max_minutes"),
        ("device", "device"),
    ):
        if getattr(args, flag, None) is not None:
            d[key] = getattr(args, flag)
    if getattr(args, "max_gaussians", None) is not None:
        d["strategy"]["max_gaussians"] = args.max_gaussians
    backend_set = any(item.split("=", 1)[0] == "raster.backend" for item in args.set or [])
    if str(d.get("device", "cpu")).startswith("cuda") and not backend_set:
        d.setdefault("raster", {})["backend"] = "gsplat"  # gsplat's CUDA rasterizer on GPUs
    if getattr(args, "appearance", False):
        d["appearance"] = d.get("appearance") or {}
    config = TrainConfig.from_dict(d)
    for key in ("max_minutes", "threads", "checkpoint_every"):
        if getattr(config, key) < 0:
            raise ValueError(f"config.{key}: expected >= 0 (0 = off), got {getattr(config, key)}")
    return config


def _read_config_file(path: str) -> dict:
    """A ``--config`` JSON file, type-checked against :class:`TrainConfig` on its own."""
    from vadgs.config import config_from_dict
    from vadgs.train.config import TrainConfig

    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"--config {p}: no such file")
    try:
        data = json.loads(p.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise ValueError(f"--config {p}: not valid JSON ({e})") from None
    config_from_dict(TrainConfig, data, where=f"--config {p}")
    return data


def _vad_config(args: argparse.Namespace) -> dict | None:
    """The ``vad`` part of the config asked for by ``--vad`` and its ablation flags (None: not asked)."""
    if not getattr(args, "vad", False):
        if getattr(args, "no_view_selection", False) or getattr(args, "no_geometric_losses", False):
            raise ValueError("--no-view-selection / --no-geometric-losses: only with --vad")
        return None
    return {"view_selection": not args.no_view_selection, "geometric_losses": not args.no_geometric_losses}


def _nest(parts: list[str], val: object) -> dict:
    return {parts[0]: val} if len(parts) == 1 else {parts[0]: _nest(parts[1:], val)}


def _scene(args: argparse.Namespace) -> object:
    """The typed reference of ``vadgs train``'s SCENE (benchmark, dgp, colmap), checking each kind's flags.

    A COLMAP model or project folder without ``scene.json`` is detected without ``--colmap-scene``
    (:func:`vadgs.train.run.scene_ref`).
    """
    from vadgs.train.run import scene_ref

    if args.dgp and args.colmap_scene:
        raise ValueError("--dgp, --colmap-scene: give one scene kind")
    path = _scene_arg(args.scene)
    kind = "dgp" if args.dgp else "colmap" if args.colmap_scene else None
    if kind is None and args.scene is not None:
        kind = scene_ref(path).kind
    kind = kind or "benchmark"
    if kind != "colmap":
        for key, flag in (
            ("images", "--images"),
            ("test_every", "--test-every"),
            ("no_normalize", "--no-normalize"),
        ):
            if getattr(args, key) not in (None, False):
                raise ValueError(
                    f"{flag}: only for a COLMAP scene (SCENE a COLMAP model or project folder), "
                    f"got a {kind} scene {path}"
                )
    elif args.colmap:
        raise ValueError("--colmap: not with a COLMAP scene, whose own SfM points initialise it")
    elif args.cameras or args.test_frames:
        raise ValueError("--cameras / --test-frames: DGP only; a COLMAP scene's split is --test-every")
    scale = args.scale if args.scale is not None else 1.0 if kind == "colmap" else 0.5
    if kind == "colmap":
        test_every = 8 if args.test_every is None else args.test_every
        return scene_ref(path, kind, images=args.images, scale=scale, test_every=test_every,
                         normalize=not args.no_normalize)  # fmt: skip
    if kind == "dgp":
        cameras = args.cameras.split(",") if args.cameras else None
        return scene_ref(path, kind, scale=scale, cameras=cameras, test_frames=args.test_frames or ())
    return scene_ref(path, kind, scale=scale)


def _summary(metrics: dict) -> str:
    t = metrics.get("test")
    parts = [
        f"{metrics['steps']} steps in {metrics['train_s']:.0f} s",
        f"{metrics['num_gaussians']} Gaussians",
    ]
    if t:
        parts.append(f"test PSNR {t['psnr']:.2f} dB, PSNR* {t['psnr_star']}, SSIM {t['ssim']:.3f}")
        raw = t.get("uncorrected")
        if raw:
            parts.append(
                f"uncorrected (no appearance transform) PSNR {raw['psnr']:.2f} dB, SSIM {raw['ssim']:.3f}"
            )
        if "all" in t["depth"]:
            parts.append(
                f"depth AbsRel {t['depth']['all']['absrel']:.3f}, "
                f"d<1.05 {t['depth']['all']['delta_1.05']:.3f}"
            )
    return "; ".join(parts)


# train flags a resumed run cannot honour: its configuration and scene are fixed by the checkpoint
_NOT_ON_RESUME = (
    ("scene", "SCENE"),
    ("sample", "--sample"),
    ("config", "--config"),
    ("set", "--set"),
    ("seed", "--seed"),
    ("max_gaussians", "--max-gaussians"),
    ("scale", "--scale"),
    ("dgp", "--dgp"),
    ("cameras", "--cameras"),
    ("test_frames", "--test-frames"),
    ("colmap", "--colmap"),
    ("colmap_scene", "--colmap-scene"),
    ("images", "--images"),
    ("test_every", "--test-every"),
    ("no_normalize", "--no-normalize"),
    ("vad", "--vad"),
    ("appearance", "--appearance"),
    ("no_view_selection", "--no-view-selection"),
    ("no_geometric_losses", "--no-geometric-losses"),
    ("overwrite", "--overwrite"),
)


# train flags a resumed run applies: TrainConfig fields of RESUMABLE_CHANGES (vadgs.train.checkpoint)
_ON_RESUME = ("iterations", "max_minutes", "device")
# train flags of the session, not of the run
_SESSION = ("out", "resume", "no_progress")


def _resume_changes(args: argparse.Namespace, out: Path) -> dict:
    """The changes ``--resume`` can honour (said aloud); the flags it cannot are rejected."""
    from vadgs.train.checkpoint import CHECKPOINT_NAME, load_checkpoint

    given = [flag for key, flag in _NOT_ON_RESUME if getattr(args, key, None) not in (None, False, [])]
    if given:
        raise ValueError(
            f"--resume: {', '.join(given)} cannot be honoured: a resumed run keeps the scene and "
            "configuration of its checkpoint (only --iterations, --max-minutes and --device can "
            "change); start a new run with --overwrite instead"
        )
    if not (out / CHECKPOINT_NAME).is_file():
        raise FileNotFoundError(f"--resume: no checkpoint in {out}")
    changes = {key: getattr(args, key) for key in _ON_RESUME if getattr(args, key, None) is not None}
    if not changes:
        return changes
    stored = load_checkpoint(out)
    cfg, step = stored["config"], int(stored["step"])
    changes = {k: v for k, v in changes.items() if cfg.get(k) != v}
    if "iterations" in changes:
        if changes["iterations"] < step:
            raise ValueError(
                f"--resume --iterations {changes['iterations']}: the run is already at step {step}"
            )
        print(
            f"NOTE: --iterations changes the run from {cfg['iterations']} to {changes['iterations']} "
            "steps; the means' learning-rate decay and VAD-GS's event window "
            "(last_event_fraction) follow the new total from here on, so the result differs "
            "from a run trained with either total from the start"
        )
    for key in ("max_minutes", "device"):
        if key in changes:
            print(f"NOTE: --{key.replace('_', '-')} changes {key} from {cfg.get(key)!r} to {changes[key]!r}")
    return changes


def _init_points(args: argparse.Namespace) -> object:
    """``--colmap``: the SfM points of a COLMAP model of the scene's views, or None.

    A function of the opened scene, which checks that the model's images are its views.
    """
    if not args.colmap:
        return None
    from vadgs.data import find_colmap_model, load_colmap, match_colmap_views

    model = find_colmap_model(args.colmap)
    if model is None:
        raise FileNotFoundError(
            f"--colmap {args.colmap}: no COLMAP model (cameras, images, points3D as .bin or "
            ".txt in it, in sparse/0, sparse or 0)"
        )

    def points(scene: object) -> object:
        match_colmap_views(scene, model, "--colmap")
        return load_colmap(model, scale=args.scale, check_files=False).points

    return points


def train(args: argparse.Namespace) -> int:
    """Train a model on a scene (``--resume`` continues the run in ``--out`` exactly)."""
    from vadgs.train.checkpoint import CHECKPOINT_NAME
    from vadgs.train.run import describe_run, train_scene

    out = _check_out_dir(args.out, create=False)
    progress = not args.no_progress
    if args.resume:
        changes = _resume_changes(args, out)
        outcome = train_scene(
            None, None, out, resume=True, config_changes=changes, progress=progress, log=print
        )
    else:
        if args.scene is None and not args.sample:
            raise ValueError("train: give a SCENE folder (or --sample for the bundled sample)")
        held = describe_run(out) if out.is_dir() else None
        if held is not None and not args.overwrite:
            raise ValueError(
                f"{out} holds a run ({held}); use --resume to continue or --overwrite to start over"
            )
        scene = _scene(args)
        args.scale = scene.scale
        config = _train_config(args)
        outcome = train_scene(
            scene,
            config,
            out,
            overwrite=args.overwrite,
            init_points=_init_points(args),
            progress=progress,
            log=print,
        )
    if not outcome.completed:
        print(f"stopped ({outcome.reason}) at step {outcome.step}; checkpoint {out / CHECKPOINT_NAME}; "
              f"continue with: vadgs train --out {out} --resume")  # fmt: skip
        return 130 if outcome.reason == "interrupted" else 0
    print(_summary(outcome.metrics))
    print(f"wrote {out / 'metrics.json'}, {out / 'ply'}")
    return 0


def _train_args(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "scene",
        nargs="?",
        help="scene folder: benchmark format (scene.json), a COLMAP model or project folder "
        "(sparse/0; detected), or DGP with --dgp",
    )
    p.add_argument("--sample", action="store_true", help="use the bundled sample scene")
    p.add_argument("--out", required=True, help="run folder (checkpoints, metrics, PLY)")
    p.add_argument("--config", help="JSON file with (part of) a TrainConfig")
    p.add_argument("--set", action="append", help="override a config field, e.g. --set init.max_points=50000")
    p.add_argument("--iterations", type=_int_at_least(0))
    p.add_argument("--seed", type=int)
    p.add_argument(
        "--max-minutes",
        type=_non_negative_float,
        help="stop and checkpoint after this much training time (0 = no limit)",
    )
    p.add_argument("--max-gaussians", type=_int_at_least(1))
    p.add_argument(
        "--scale",
        type=_positive_float,
        default=None,
        help="image resolution factor (default 0.5 = 240x144 for the benchmark; 1.0 for COLMAP)",
    )
    p.add_argument("--dgp", action="store_true", help="SCENE is a DGP scene folder")
    p.add_argument("--cameras", help="DGP: comma-separated camera names")
    p.add_argument("--test-frames", type=int, nargs="*", help="DGP: held-out frames (samples)")
    p.add_argument(
        "--colmap-scene",
        action="store_true",
        help="SCENE is a COLMAP model or project folder (detected without it when there is no scene.json)",
    )
    p.add_argument("--images", help="COLMAP scene: the images folder (default: images/ next to the model)")
    p.add_argument(
        "--test-every",
        type=_int_at_least(0),
        help="COLMAP scene: hold out every N-th image in name order, index %% N == 0 (default 8; 0 = none)",
    )
    p.add_argument(
        "--no-normalize",
        action="store_true",
        help="COLMAP scene: keep COLMAP's frame and scale (default: cameras centred, up +z, "
        "median camera-to-point depth 10)",
    )
    p.add_argument(
        "--colmap",
        help="COLMAP model of this scene's views (same image names, same world frame) whose points "
        "are added to the initialisation",
    )
    p.add_argument(
        "--resume",
        action="store_true",
        help="continue the run in --out from its checkpoint (only --iterations, --max-minutes, "
        "--device may change it)",
    )
    p.add_argument(
        "--overwrite",
        action="store_true",
        help="--out may hold a previous run: its files are removed and training starts over",
    )
    p.add_argument(
        "--device",
        help="torch device for the model and losses (cpu, cuda, cuda:1; default cpu); on CUDA the "
        "renderer is gsplat's (raster.backend=gsplat) unless --set raster.backend=torch",
    )
    p.add_argument("--vad", action="store_true", help="VAD-GS visibility-aware densification (the paper)")
    p.add_argument(
        "--no-view-selection", action="store_true", help="ablation: consecutive frames (with --vad)"
    )
    p.add_argument(
        "--no-geometric-losses", action="store_true", help="ablation: no normal/depth losses (with --vad)"
    )
    p.add_argument(
        "--appearance",
        action="store_true",
        help="learn a colour transform per camera (real rigs with differently exposed cameras); "
        "tune with --set appearance.per_frame=true, appearance.lr=..., appearance.reg=...",
    )
    p.add_argument("--no-progress", action="store_true")


train.add_arguments = _train_args  # type: ignore[attr-defined]


def eval_run(args: argparse.Namespace) -> int:
    """Evaluate a run's checkpoint on the test split or the novel views (PSNR, PSNR*, SSIM, depth, #G).

    ``--split test`` writes ``RUN/eval.json`` (one :class:`~vadgs.train.evaluate.EvalMetrics`);
    ``--split novel`` writes ``RUN/eval_novel.json``: ``{"split", "step", "groups": {group: metrics}}``.
    """
    from vadgs.train.evaluate import evaluate_split

    run = load_run(args.run)
    groups = evaluate_split(
        run.model,
        run.scene,
        args.split,
        config=run.config.raster,
        progress=not args.no_progress,
        appearance=run.appearance,
    )
    step = run.step
    if args.split == "test":
        m = groups["test"].to_dict()
        m["step"] = step
        path = _run_dir(args.run) / "eval.json"
        shown = {k: v for k, v in m.items() if k != "per_view"}
        note = m["lpips_note"]
    else:
        m = {"split": args.split, "step": step, "groups": {k: g.to_dict() for k, g in groups.items()}}
        path = _run_dir(args.run) / f"eval_{args.split}.json"
        shown = {k: {kk: vv for kk, vv in g.items() if kk != "per_view"} for k, g in m["groups"].items()}
        note = next(iter(m["groups"].values()))["lpips_note"]
    write_json(path, m)
    print(json.dumps(shown, indent=2))
    if note:
        print(note)
    print(f"wrote {path}")
    return 0


def _eval_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("run", help="run folder (or its checkpoint.pt)")
    p.add_argument(
        "--split",
        choices=("test", "novel"),
        default="test",
        help="test views (eval.json) or the novel views by group, e.g. shifted ±2 m (eval_novel.json)",
    )
    p.add_argument("--no-progress", action="store_true")


eval_run.add_arguments = _eval_args  # type: ignore[attr-defined]


def render_run(args: argparse.Namespace) -> int:
    """Render a run's test views as PNG panels, or a video along the ego path (``--video``).

    Panels: image, GT, error, depth, GT depth, normals per view. ``--video OUT.mp4``: one rig
    camera along the ego path (``--trajectory ego``) or shifted in the ego frame
    (``shift:METRES``, + = left; ``shift:X,Y,Z``), colour | depth | normals side by side, moving
    cars at their poses (interpolated between frames with ``--frames-between``).
    """
    run = load_run(args.run)
    model, scene, config = run.model, run.scene, run.config
    if args.video:
        from vadgs.train.video import ego_trajectory, parse_trajectory, render_video

        camera = args.camera or ("front" if "front" in scene.cameras_info else scene.camera_names[0])
        traj = ego_trajectory(scene, camera, parse_trajectory(args.trajectory), args.frames_between)
        info = render_video(
            model, scene, args.video, traj, fps=args.fps, config=config.raster, progress=not args.no_progress
        )
        print(
            f"wrote {info.path}: {info.num_frames} frames of {info.size[1]}x{info.size[0]} at {args.fps} fps"
        )
        return 0
    from vadgs.train.evaluate import save_test_panels

    views = args.views if args.views else None
    out = _check_out_dir(args.out if args.out else _run_dir(args.run) / "renders")
    paths = save_test_panels(model, scene, out, views, config.raster, not args.no_progress, run.appearance)
    print(f"wrote {len(paths)} panels to {out}")
    return 0


def _render_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("run", help="run folder (or its checkpoint.pt)")
    p.add_argument("--out", help="output folder of the panels (default RUN/renders)")
    p.add_argument("--views", type=int, nargs="*", help="view indices (default: the test views)")
    p.add_argument("--video", help="write a video (.mp4) along --trajectory instead of panels")
    p.add_argument(
        "--trajectory",
        default="ego",
        help="ego (the rig's path), shift:METRES (sideways in the ego frame, + = left) or shift:X,Y,Z",
    )
    p.add_argument("--camera", help="rig camera of the video (default front)")
    p.add_argument("--fps", type=float, default=10.0)
    p.add_argument(
        "--frames-between",
        type=int,
        default=0,
        help="poses interpolated between consecutive frames (slerp / linear; cars likewise)",
    )
    p.add_argument("--no-progress", action="store_true")


render_run.add_arguments = _render_args  # type: ignore[attr-defined]


def export_run(args: argparse.Namespace) -> int:
    """Export the world at one frame as one viewer-ready 3DGS PLY (cars posed, SH rotated) and the sky map.

    Writes ``OUT/world_frame<F>.ply`` (or with ``--inria`` the INRIA model layout
    ``OUT/point_cloud/iteration_<step>/point_cloud.ply``, ``cameras.json``, ``cfg_args``) and
    ``OUT/sky.png`` / ``sky.json``; see :func:`vadgs.train.export.export_world`.
    """
    from vadgs.train.export import export_world

    run = load_run(args.run)
    model, scene = run.model, run.scene
    frame, _ = frame_position(scene, args.frame, "--frame")
    out = Path(args.out) if args.out else _run_dir(args.run) / "export" / f"frame{frame:03d}"
    res = export_world(model, scene, frame, out, inria=args.inria, iteration=run.step)
    print(f"wrote {res.ply} ({res.num_gaussians} Gaussians, world at frame {frame}) and {res.sky_png}")
    return 0


def _export_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("run", help="run folder (or its checkpoint.pt)")
    p.add_argument("--frame", type=int, help="the scene's frame index (default: its first frame)")
    p.add_argument("--out", help="output folder (default RUN/export/frame<F>)")
    p.add_argument(
        "--inria",
        action="store_true",
        help="INRIA model layout (point_cloud/iteration_N/, cameras.json, cfg_args)",
    )


export_run.add_arguments = _export_args  # type: ignore[attr-defined]


def view_run(args: argparse.Namespace) -> int:
    """Open a run in the browser (viser): Gaussians, cars at a frame slider, camera frusta, VAD-GS additions.

    Serves ``http://HOST:PORT`` until Ctrl+C (or ``--timeout`` seconds); see :mod:`vadgs.viewer`.
    """
    try:
        import viser
    except ImportError:
        raise ImportError("vadgs view needs viser: pip install 'vadgs[viewer]'") from None
    from vadgs.viewer import build_viewer

    run = load_run(args.run)
    model, scene = run.model, run.scene
    _, position = frame_position(scene, args.frame, "--frame")
    server = viser.ViserServer(host=args.host, port=args.port, verbose=False)
    try:
        viewer = build_viewer(model, scene, server, position, max_gaussians=args.max_gaussians)
        shown = sum(int(g.rows.numel()) for g in viewer.groups)
        print(
            f"viewing {_run_dir(args.run)}: {shown} of {model.num_gaussians} Gaussians, "
            f"{len(model.track_ids)} moving objects, {len(scene.frames)} frames"
        )
        host = "localhost" if args.host in ("0.0.0.0", "::") else args.host
        print(f"open http://{host}:{server.get_port()} (Ctrl+C to stop)", flush=True)
        deadline = None if args.timeout is None else time.monotonic() + args.timeout
        while deadline is None or time.monotonic() < deadline:
            time.sleep(0.2)
    except KeyboardInterrupt:
        pass
    finally:
        server.stop()
    return 0


def _view_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("run", help="run folder (or its checkpoint.pt)")
    p.add_argument("--host", default="0.0.0.0", help="interface to listen on (default 0.0.0.0: all)")
    p.add_argument(
        "--port", type=_int_at_least(1), default=8080, help="port (default 8080; the next free one if taken)"
    )
    p.add_argument("--frame", type=int, help="the scene's frame index shown first (default: its first frame)")
    p.add_argument(
        "--max-gaussians",
        type=_int_at_least(1),
        default=1_000_000,
        help="send at most this many Gaussians to the browser (a random subset; default 1,000,000)",
    )
    p.add_argument("--timeout", type=_positive_float, help="stop serving after this many seconds")


view_run.add_arguments = _view_args  # type: ignore[attr-defined]


def demo(args: argparse.Namespace) -> int:
    """Train briefly on the bundled sample scene; write metrics.json and a PNG panel."""
    from vadgs.data import load_scene
    from vadgs.train.config import TrainConfig
    from vadgs.train.evaluate import render_test_view
    from vadgs.train.trainer import Trainer
    from vadgs.viz import colorize_depth, image_to_uint8, save_panel

    out = _check_out_dir(args.out)
    ref = {"kind": "benchmark", "path": str(_scene_arg(None)), "scale": DEMO_SCALE}
    scene = load_scene(ref["path"], scale=DEMO_SCALE)
    config = TrainConfig.from_dict(_deep_update(TrainConfig().to_dict(), DEMO_CONFIG))
    if args.iterations is not None:
        config = config.replace(iterations=args.iterations)
    if not args.baseline:
        from vadgs.train.reconstruct import ReconstructConfig
        from vadgs.train.vad import VisibilityDensifyConfig

        vad = VisibilityDensifyConfig(max_instances=3, reconstruct=ReconstructConfig(max_crop=64))
        config = dataclasses.replace(config, vad=vad)
    t0 = time.perf_counter()
    trainer = Trainer(scene, config, out_dir=out, scene_ref=ref, progress=not args.no_progress)
    strategy = trainer.strategy if config.vad is not None else None
    snapshots: list[dict] = []  # the largest addition only, for the completion figure
    if strategy is not None:
        strategy.on_addition = lambda snap: snapshots.__setitem__(
            slice(None), [max([*snapshots, snap], key=lambda x: x["added"])]
        )
    result = trainer.train()
    metrics = finish_run(trainer, out, result, not args.no_progress, started=t0)
    view = scene.test_views[len(scene.test_views) // 2]
    r = render_test_view(trainer.model, scene, view, config.raster)
    gtd = scene.load_depths([view])[0, 0]
    vmax = float(gtd[gtd > 0].quantile(0.98))
    pv = next(p for p in metrics["test"]["per_view"] if p["view"] == view)
    png = save_panel(
        [image_to_uint8(r.color[0]), image_to_uint8(scene.load_images([view])[0]),
         colorize_depth(r.raster.depth[0, 0], None, vmax), colorize_depth(gtd, None, vmax)],
        [f"test render ({pv['psnr']:.2f} dB)", "ground truth", "rendered depth", "ground-truth depth"],
        out / "demo_panel.png",
        columns=2,
    )  # fmt: skip
    if strategy is not None:
        if snapshots:
            _completion_panel(trainer, snapshots, out / "demo_completion.png", vmax)
            print(f"wrote {out / 'demo_completion.png'}")
    print(_summary(metrics))
    print(f"wrote {out / 'metrics.json'} and {png}")
    return 0


def _completion_panel(trainer, snapshots: list, path: Path, vmax: float) -> Path:
    """The instance that got the most new Gaussians: its reference view before and after."""
    from vadgs.viz import colorize_depth, image_to_uint8, save_panel

    snap = max(snapshots, key=lambda s: s["added"])
    scene, view = trainer.scene, snap["view"]
    after = trainer.render_view(view)
    mask = (scene.load_instances([view])[0] == snap["instance"]).float()
    image = scene.load_images([view])[0]
    name = scene.instances.get(snap["instance"])
    label = name.name if name else str(snap["instance"])
    gt = scene.load_depths([view])[0, 0]
    images = [
        image_to_uint8(image * (0.35 + 0.65 * mask)),
        colorize_depth(gt, None, vmax),
        colorize_depth(snap["depth"], None, vmax),
        colorize_depth(after.raster.depth[0, 0].detach(), None, vmax),
    ]
    titles = [
        f"flagged: {label} (view {view})",
        "ground-truth depth",
        f"rendered depth at step {snap['step']}",
        f"after: +{snap['added']} MVS Gaussians",
    ]
    return save_panel(images, titles, path, columns=2)


#: The demo's configuration (merged into the TrainConfig defaults): the bundled sample at 120x72,
#: about 14k Gaussians, 250 steps.
DEMO_SCALE = 0.5
DEMO_CONFIG: dict = {
    "iterations": 250,
    "init": {"voxel_size": 0.2, "max_points": 12_000, "max_object_points": 2_000, "sh_degree": 1},
    "strategy": {"refine_start_iter": 60, "refine_every": 40, "refine_stop_iter": 200, "reset_every": 0,
                 "max_gaussians": 25_000},
    "sh_degree_interval": 100,
    "checkpoint_every": 0,
    "log_every": 10,
}  # fmt: skip


def _demo_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--out", default="outputs/demo", help="output folder")
    p.add_argument("--iterations", type=_int_at_least(0), help="override the demo's iteration count")
    p.add_argument("--baseline", action="store_true", help="standard densification only (no VAD-GS)")
    p.add_argument("--no-progress", action="store_true")


demo.add_arguments = _demo_args  # type: ignore[attr-defined]


def convert(args: argparse.Namespace) -> int:
    """Convert a nuScenes scene or a Waymo v2 segment into the benchmark format (``scene.json``)."""
    from vadgs.data import export_scene, load_nuscenes, load_waymo

    cameras = args.cameras.split(",") if args.cameras else None
    frames = None
    if args.frames:
        start, _, stop = args.frames.partition(":")
        frames = range(int(start or 0), int(stop)) if stop else [int(start)]
    if args.dataset == "nuscenes":
        scene = load_nuscenes(
            args.src, args.scene, version=args.version, cameras=cameras, scale=args.scale, frames=frames
        )
    else:
        lasers = None if args.no_lidar else ("TOP",)  # --no-lidar: a segment without the lidar component
        scene = load_waymo(
            args.src, args.scene, cameras=cameras, scale=args.scale, frames=frames, lasers=lasers
        )
    path = export_scene(scene, args.out, lidar=not args.no_lidar)
    print(f"{scene!r} -> {path}")
    return 0


def _convert_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("dataset", choices=["nuscenes", "waymo"])
    p.add_argument("src", help="nuScenes dataroot, or the Waymo v2 split folder holding the components")
    p.add_argument("--scene", required=True, help="nuScenes scene name (scene-0061) or Waymo segment name")
    p.add_argument("--out", required=True, help="output folder for scene.json, images/, lidar/")
    p.add_argument("--version", default="v1.0-mini", help="nuScenes table folder (v1.0-mini, v1.0-trainval)")
    p.add_argument("--cameras", help="comma-separated camera names (default all)")
    p.add_argument("--scale", type=float, default=1.0, help="image resolution factor")
    p.add_argument("--frames", help="frame positions START:STOP (keyframes for nuScenes), default all")
    p.add_argument("--no-lidar", action="store_true", help="no LiDAR (Waymo: needs no lidar file)")


convert.add_arguments = _convert_args  # type: ignore[attr-defined]


def _batch_train(text: str) -> tuple[object, str | None, dict]:
    """``vadgs batch --train-args``: the TrainConfig, scene kind and scene options they give.

    Parsed once, in the driver, with ``vadgs train``'s own flags, so a bad argument fails the
    batch before any scene starts; the flags of one run folder (``--out``, ``--resume``, ...) are
    refused.
    """
    import shlex

    p = argparse.ArgumentParser(prog="vadgs batch --train-args", add_help=False, exit_on_error=False)
    _train_args(p)
    try:
        targs, extra = p.parse_known_args(["--out", ".", *shlex.split(text)])
    except argparse.ArgumentError as e:
        raise ValueError(f"--train-args: {e}") from None
    if extra:
        raise ValueError(f"--train-args: unrecognized arguments: {' '.join(extra)}")
    for key, flag in (("scene", "SCENE"), ("sample", "--sample"), ("resume", "--resume"),
                      ("overwrite", "--overwrite"), ("colmap", "--colmap")):  # fmt: skip
        if getattr(targs, key) not in (None, False):
            raise ValueError(
                f"--train-args: {flag} is not for a batch (the scenes and run folders are its own)"
            )
    if targs.dgp and targs.colmap_scene:
        raise ValueError("--train-args: --dgp, --colmap-scene: give one scene kind")
    kind = "dgp" if targs.dgp else "colmap" if targs.colmap_scene else None
    options: dict = {}
    for key, name in (("scale", "scale"), ("images", "images"), ("test_every", "test_every")):
        if getattr(targs, key) is not None:
            options[name] = getattr(targs, key)
    if targs.no_normalize:
        options["normalize"] = False
    if targs.cameras:
        options["cameras"] = targs.cameras.split(",")
    if targs.test_frames:
        options["test_frames"] = targs.test_frames
    return _train_config(targs), kind, options


def batch(args: argparse.Namespace) -> int:
    """Train many scenes on Ray, one task each, retried and resumed on failure (needs vadgs[ray])."""
    from vadgs.batch import BatchConfig, run_batch

    train, kind, options = _batch_train(args.train_args)
    config = BatchConfig(
        address=args.address,
        cpus_per_scene=args.cpus_per_scene,
        gpus_per_scene=args.gpus_per_scene,
        threads=args.threads or 0,
        max_retries=args.max_retries,
        train=train,
        scene_kind=kind,
        scene_options=options,
        progress=not args.no_progress,
    )
    try:
        summary = run_batch(args.scenes, args.out, config)
    except ImportError as e:
        print(f"vadgs batch: error: {e}", file=sys.stderr)
        return 2
    print(summary.to_markdown())
    print(f"wrote {Path(summary.out_dir) / 'summary.json'}, {Path(summary.out_dir) / 'summary.md'}")
    return 1 if summary.failed else 0


def _batch_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("scenes", nargs="+", metavar="SCENE", help="scene folders (one run folder each)")
    p.add_argument("--out", required=True, help="batch folder: run folders, summary.json, summary.md")
    p.add_argument(
        "--address", help="Ray cluster: auto, ray://HEAD:10001 or HOST:6379 (default: start a local Ray)"
    )
    p.add_argument("--cpus-per-scene", type=float, default=1.0, help="Ray CPUs per task (default 1)")
    p.add_argument("--gpus-per-scene", type=float, default=0.0, help="Ray GPUs per task (default 0)")
    p.add_argument("--max-retries", type=int, default=3, help="retries of a task whose worker/node died")
    p.add_argument(
        "--train-args",
        default="",
        help='arguments of each vadgs train, e.g. --train-args="--vad --iterations 3000" (with "=")',
    )
    p.add_argument("--no-progress", action="store_true", help="no line per finished run")


batch.add_arguments = _batch_args  # type: ignore[attr-defined]


def check(args: argparse.Namespace) -> int:
    """Validate a scene's metadata and files; print a table (exit 1 when a check fails)."""
    from vadgs.data import load_dgp, validate_scene

    if args.dgp:
        try:
            scene = load_dgp(_scene_arg(args.scene), scale=args.scale, validate="none")
        except (ValueError, FileNotFoundError) as e:
            print(f"error  {args.scene}: {e}")
            return 1
        report = validate_scene(scene, full=args.full)
    else:
        report = validate_scene(_scene_arg(args.scene), full=args.full, scale=args.scale)
    print(report.format_table())
    level = "every file decoded" if args.full else "headers only; --full decodes every file"
    n = len(report.errors)
    print(f"{report.scene}: {'ok' if report.ok else f'{n} error(s)'} ({len(report.rows)} checks, {level})")
    return 0 if report.ok else 1


def _check_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("scene", nargs="?", help="scene folder (default: the bundled sample)")
    p.add_argument("--full", action="store_true", help="decode every image, depth map, instance map, sweep")
    p.add_argument("--scale", type=_positive_float, default=1.0, help="resolution factor to check against")
    p.add_argument("--dgp", action="store_true", help="SCENE is a DGP scene folder")


check.add_arguments = _check_args  # type: ignore[attr-defined]

COMMANDS: dict[str, Callable[[argparse.Namespace], int]] = {
    "check": check,
    "visibility": visibility,
    "train": train,
    "eval": eval_run,
    "render": render_run,
    "export": export_run,
    "view": view_run,
    "demo": demo,
    "convert": convert,
    "batch": batch,
}


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``vadgs`` console script."""
    parser = argparse.ArgumentParser(
        prog="vadgs", description="VAD-GS: visibility-aware densification for 3DGS"
    )
    parser.add_argument(
        "--threads",
        type=_int_at_least(1),
        default=None,
        help="torch CPU threads (>= 1; default: torch's, all cores)",
    )
    parser.add_argument("--debug", action="store_true", help="show the traceback of an error")
    sub = parser.add_subparsers(dest="command", required=True)
    for name, fn in COMMANDS.items():
        p = sub.add_parser(name, help=(fn.__doc__ or "").strip().splitlines()[0])
        fn.add_arguments(p)  # type: ignore[attr-defined]
    args = parser.parse_args(argv)
    try:
        with _torch_threads(args.threads), _colmap_log_level(0 if args.debug else None):
            return COMMANDS[args.command](args)
    except KeyboardInterrupt:
        if args.debug:
            raise
        print(f"vadgs {args.command}: interrupted", file=sys.stderr)
        return 130
    except Exception as e:
        if args.debug:
            traceback.print_exc()
        print(f"vadgs {args.command}: error: {_one_line(e)}", file=sys.stderr)
        return 3 if isinstance(e, FloatingPointError) else 2


@contextlib.contextmanager
def _torch_threads(threads: int | None):
    """``torch.set_num_threads(threads)`` for the command (None: leave it; all cores in a new process).

    The previous count comes back afterwards, so ``main`` called in-process (tests, notebooks,
    ``vadgs batch``) leaves the process as it found it.
    """
    before = torch.get_num_threads()
    if threads:
        torch.set_num_threads(threads)
    try:
        yield
    finally:
        torch.set_num_threads(before)


@contextlib.contextmanager
def _colmap_log_level(level: int | None):
    """The pycolmap log level for the command (``--debug``: everything), restored afterwards."""
    from vadgs.data import colmap

    before = colmap.COLMAP_LOG_LEVEL
    if level is not None:
        colmap.COLMAP_LOG_LEVEL = level
    try:
        yield
    finally:
        colmap.COLMAP_LOG_LEVEL = before


def _one_line(e: BaseException) -> str:
    """An exception as one line; unexpected kinds keep their type name and point to ``--debug``.

    Notes added to the exception (``add_note``: e.g. the trainer's "last good checkpoint: ...")
    follow, separated by "; ".
    """
    text = " ".join(str(e).split()) or repr(e)
    notes = "".join("; " + " ".join(str(n).split()) for n in getattr(e, "__notes__", None) or ())
    if isinstance(e, (ValueError, FileNotFoundError, FloatingPointError)):
        return text + notes
    if isinstance(e, OSError) and e.filename is not None:
        return f"{e.filename}: {e.strerror or text}{notes}"
    return f"{type(e).__name__}: {text}{notes} (--debug shows the traceback)"


if __name__ == "__main__":
    raise SystemExit(main())
