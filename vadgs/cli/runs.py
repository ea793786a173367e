"""Commands on a trained run: ``vadgs eval``, ``vadgs render``, ``vadgs export``, ``vadgs view``."""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

from vadgs.cli._common import _check_out_dir, _int_at_least, _positive_float, _run_dir
from vadgs.io import write_json
from vadgs.train.run import frame_position, load_run


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
