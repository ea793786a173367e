"""Commands on a trained run: ``vadgs eval``, ``vadgs render``, ``vadgs export``, ``vadgs view``.

Each finds the run's scene where the run recorded it (absolute, from any current folder), checks
its fingerprint, and takes ``--scene FOLDER`` for a run whose scene moved
(:func:`~vadgs.train.run.load_run`). Those that write into the run folder hold its lock
(:class:`~vadgs.runlock.RunLock`) while they run.
"""

from __future__ import annotations

import contextlib
import json
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Literal

import tyro

from vadgs.checks import checked, float_field, int_field
from vadgs.cli._common import Command, Flag, Positional, check_out_dir, lidar_depth_line, run_dir
from vadgs.data.scene import Scene
from vadgs.io import write_json
from vadgs.runfolder import check_output_folder, read_manifest, record_files, recorded_files
from vadgs.runlock import RunLock
from vadgs.train.results.trajectory import MAX_FRAMES
from vadgs.train.run import Run, frame_position, load_run
from vadgs.train.scenes import FINGERPRINT_CHECKS

__all__ = ["EvalCommand", "ExportCommand", "RenderCommand", "ViewCommand"]

#: The run a command reads: its folder or its ``checkpoint.pt``.
RunArg = Annotated[str, Positional, tyro.conf.arg(metavar="RUN")]

#: ``--scene``: the run's scene folder when it moved.
SceneOpt = Annotated[str | None, tyro.conf.arg(metavar="FOLDER")]


def _writing(run: str | Path, into: str | Path, command: str) -> contextlib.AbstractContextManager:
    """The run folder's lock while a command writes ``into`` it (nothing when it writes elsewhere)."""
    folder = run_dir(run).resolve()
    into = Path(into).resolve()
    if folder.is_dir() and (into == folder or into.is_relative_to(folder)):
        read_manifest(folder)  # an unreadable manifest: refused before anything is written
        return RunLock(folder, command)
    return contextlib.nullcontext()


def _scene(run: Run) -> Scene:
    """The scene of a run loaded with ``open=True`` (every command here loads it so)."""
    if run.scene is None:
        raise ValueError("run: expected its scene opened (load_run(open=True)), got None")
    return run.scene


def _owner(run: str | Path, into: str | Path) -> Path:
    """The folder whose manifest records what a command writes ``into``.

    The run's, when ``into`` is inside the run folder, else ``into`` itself (an output folder of its own).
    """
    folder = run_dir(run).resolve()
    resolved = Path(into).resolve()
    return run_dir(run) if resolved == folder or resolved.is_relative_to(folder) else Path(into)


def _check_into(run: str | Path, into: str | Path, flag: str = "--out") -> Path:
    """Refuse an output folder outside the run that is neither empty nor written by vadgs."""
    owner = _owner(run, into)
    if owner == Path(into):
        check_output_folder(into, flag, "vadgs output")
    return owner


def _scene_record(run) -> dict:
    """What ``eval.json`` says of the scene it used: name, kind, path, fingerprint and what it checked."""
    ref = run.scene_ref or {}
    return {
        "name": run.scene.name,
        **{k: ref.get(k) for k in ("kind", "path", "fingerprint")},
        "fingerprint_checks": FINGERPRINT_CHECKS,
    }


def _checked(record: dict) -> str:
    """The line ``vadgs eval`` prints on the scene it checked against the run's fingerprint."""
    return f"{record['path']} (fingerprint {record['fingerprint']}: {record['fingerprint_checks']})"


@dataclass(frozen=True)
class EvalCommand(Command):
    """Evaluate a run's checkpoint on the test split or the novel views (PSNR, PSNR*, SSIM, depth, #G).

    ``--split test`` writes ``RUN/eval.json`` (one :class:`~vadgs.train.results.evaluate.EvalMetrics`);
    ``--split novel`` writes ``RUN/eval_novel.json``: ``{"split", "step", "groups": {group: metrics}}``.
    """

    run: RunArg
    """run folder (or its checkpoint.pt)"""
    split: Literal["test", "novel"] = "test"
    """test views (eval.json) or the novel views by group, e.g. shifted ±2 m (eval_novel.json)"""
    scene: SceneOpt = None
    """the run's scene folder if it moved, checked by its fingerprint (None: where the run recorded it)"""
    no_progress: Flag = False
    """no progress bar"""

    def main(self) -> int:
        """Evaluate the run and write the JSON; 0."""
        from vadgs.train.results.evaluate import evaluate_split

        folder = run_dir(self.run)
        with _writing(self.run, folder, "vadgs eval"):
            run = load_run(self.run, scene=self.scene)
            groups = evaluate_split(
                run.model,
                _scene(run),
                self.split,
                config=run.config.raster,
                progress=not self.no_progress,
                appearance=run.appearance,
            )
            if self.split == "test":
                m = groups["test"].to_dict()
                m["step"] = run.step
                path = folder / "eval.json"
                shown = {k: v for k, v in m.items() if k != "per_view"}
                note = m["lpips_note"]
            else:
                groups_d = {k: g.to_dict() for k, g in groups.items()}
                m = {"split": self.split, "step": run.step, "groups": groups_d}
                path = folder / f"eval_{self.split}.json"
                shown = {k: {kk: vv for kk, vv in g.items() if kk != "per_view"} for k, g in groups_d.items()}
                note = next(iter(groups_d.values()))["lpips_note"]
            m["scene"] = _scene_record(run)
            record_files(folder, [write_json(path, m)])
        print(json.dumps(shown, indent=2))
        if note:
            print(note)
        metrics = [shown] if self.split == "test" else list(shown.values())
        if any(g.get("psnr_star") is None for g in metrics):
            print(
                "psnr_star: null: PSNR* (moving objects only) needs moving-object pixels; the views have none"
                if len(run.model.track_ids)
                else "psnr_star: null: PSNR* scores moving objects only, and "
                + ("photos have none" if _scene(run).is_photo_collection else "the scene has none")
            )
        for name, g in zip(["test"] if self.split == "test" else list(shown), metrics, strict=True):
            if "lidar" in g["depth"]:
                print(("" if self.split == "test" else f"{name}: ") + lidar_depth_line(g["depth"]["lidar"]))
        print(f"scene checked: {_checked(m['scene'])}")
        print(f"wrote {path}")
        return 0


@dataclass(frozen=True)
class RenderCommand(Command):
    """Render a run's test views as PNG panels, or a video along a camera path (``--video``).

    Panels: image, GT, error, depth, GT depth, normals per view. ``--video OUT.mp4``: colour |
    depth | normals side by side (``--video-layout color``: the colour alone; the depth colours
    keep one range over the video, from 8 frames along the path) along ``--trajectory``: one rig
    camera along the ego path (``ego``) or shifted in the ego frame (``shift:METRES``, + = left;
    ``shift:X,Y,Z``), moving cars at their poses (interpolated between frames with
    ``--frames-between``); or, on any scene (a photo collection has no ego path), a smooth path
    through the training cameras (``interpolate``) or a circle around the scene's centre
    (``orbit``, ``orbit:FRAMES``).
    ``--trajectory list`` prints what the run's scene offers.

    Before any rendering: the video's name (``.mp4``, ``.mov`` or ``.mkv``, at most 241 bytes), its
    folder (writable), and its length: at most ``--max-frames`` frames (``orbit:FRAMES``,
    ``--frames-between``). A camera path from which no Gaussian is in view (``shift:1e30``) is
    rendered with a one-line warning.
    """

    run: RunArg
    """run folder (or its checkpoint.pt)"""
    out: str | None = None
    """output folder of the panels (default RUN/renders)"""
    views: tuple[int, ...] = ()
    """view indices (default: the test views)"""
    video: str | None = None
    """write a video (.mp4, .mov or .mkv) along --trajectory instead of panels"""
    video_layout: Literal["strip", "color"] = "strip"
    """the video's frames: colour | depth | normals side by side (strip), or the colour alone (color)"""
    trajectory: str | None = None
    """ego (the rig's path), shift:METRES (sideways in the ego frame, + = left), shift:X,Y,Z,
    interpolate (through the training cameras), orbit or orbit:FRAMES (around the centre);
    list: print those the scene offers (default: ego where there is one, else interpolate)"""
    camera: str | None = None
    """camera of the video (default front, else the camera of the most training views)"""
    fps: float = checked(10.0, float_field(0, lo_open=True))
    """frames per second of the video"""
    frames_between: int | None = checked(None, int_field(0, optional=True))
    """poses between consecutive frames (ego, shift; default 0) or training cameras
    (interpolate; default 8)"""
    max_frames: int = checked(MAX_FRAMES, int_field(1))
    """the most frames a video may have (orbit:FRAMES, --frames-between), checked before rendering"""
    scene: SceneOpt = None
    """the run's scene folder if it moved, checked by its fingerprint (None: where the run recorded it)"""
    no_progress: Flag = False
    """no progress bar"""

    def _check_video(self) -> None:
        """The video's name, folder and the counts that need no scene, before the run is loaded.

        Here rather than in ``__post_init__``: tyro wraps that message to its box's width, which
        would break a long path or count in two.
        """
        if self.frames_between is not None and self.frames_between >= self.max_frames:
            n = self.frames_between  # the whole video is longer still
            raise ValueError(f"--frames-between {n}: {_too_many(self.max_frames, n)}")
        spec = (self.trajectory or "").strip()
        count = spec[len("orbit:") :] if spec.startswith("orbit:") else ""
        digits = count.lstrip("0")
        if count.isascii() and count.isdigit() and (len(digits) > 18 or int(digits or 0) > self.max_frames):
            raise ValueError(f"--trajectory {spec}: {_too_many(self.max_frames, count)}")
        if self.video is not None:
            from vadgs.train.results.video import check_video_path

            try:
                check_video_path(self.video)
            except ValueError as e:
                raise ValueError(f"--video {e}") from None
            # nothing rendered for a folder that cannot take the video
            check_out_dir(Path(self.video).parent, "--video", create=False)

    def main(self) -> int:
        """Write the panels or the video; 0."""
        self._check_video()
        into = Path(self.video).parent if self.video else (self.out or run_dir(self.run) / "renders")
        with _writing(self.run, into, "vadgs render"):
            return self._render()

    def _render(self) -> int:
        run = load_run(self.run, scene=self.scene)
        model, scene, config = run.model, _scene(run), run.config
        if self.video or self.trajectory == "list":
            from vadgs.train.results.trajectory import (
                default_video_camera,
                make_trajectory,
                trajectory_choices,
                trajectory_length,
            )
            from vadgs.train.results.video import render_video

            try:  # the library names its arguments; here they are flags
                camera = self.camera or default_video_camera(scene)
                choices = trajectory_choices(scene, camera)
                spec = self.trajectory or choices[0]
                if spec == "list":
                    print(f"trajectories of scene {scene.name!r}, camera {camera}: {', '.join(choices)}")
                    print(f"default: {choices[0]}")
                    return 0
                count = trajectory_length(scene, spec, camera, self.frames_between)
                if count <= self.max_frames:  # checked before a pose is built
                    traj = make_trajectory(scene, spec, camera, self.frames_between, max_frames=None)
            except ValueError as e:
                text = str(e).replace("frames_between:", "frames-between:", 1)
                flags = ("trajectory:", "camera:", "frames-between:")
                raise ValueError(f"--{text}" if text.startswith(flags) else text) from None
            if count > self.max_frames:
                given = f"--trajectory {spec}"
                if self.frames_between is not None:
                    given += f" --frames-between {self.frames_between}"
                raise ValueError(f"{given}: {_too_many(self.max_frames, count)}")
            _warn_out_of_view(model, scene, traj, spec)
            assert self.video is not None  # --trajectory list without --video returned above
            info = render_video(
                model,
                scene,
                self.video,
                traj,
                fps=self.fps,
                config=config.raster,
                progress=not self.no_progress,
                layout=self.video_layout,
            )
            assert info.size is not None  # a trajectory has at least one pose
            size = f"{info.size[1]}x{info.size[0]}"
            print(
                f"wrote {info.path}: {info.num_frames} frames of {size} at {self.fps} fps "
                f"(trajectory {spec}, camera {camera})"
            )
            return 0
        from vadgs.train.results.evaluate import save_test_panels

        out = Path(self.out) if self.out else run_dir(self.run) / "renders"
        owner = _check_into(self.run, out)
        out = check_out_dir(out)
        views = list(self.views) or None
        paths = save_test_panels(
            model, scene, out, views, config.raster, not self.no_progress, run.appearance
        )
        record_files(owner, paths)
        print(f"wrote {len(paths)} panels to {out}")
        return 0


@dataclass(frozen=True)
class ExportCommand(Command):
    """Export the world at one frame as one viewer-ready 3DGS PLY (cars posed, SH rotated) and the sky map.

    Writes ``OUT/world_frame<F>.ply`` (or with ``--inria`` the INRIA model layout
    ``OUT/point_cloud/iteration_<step>/point_cloud.ply``, ``cameras.json``, ``cfg_args``) and
    ``OUT/sky.png`` / ``sky.json``; see :func:`vadgs.train.results.export.export_world`.
    """

    run: RunArg
    """run folder (or its checkpoint.pt)"""
    frame: int | None = None
    """the scene's frame index (default: its first frame)"""
    out: str | None = None
    """output folder (default RUN/export/frame<F>)"""
    inria: Flag = False
    """INRIA model layout (point_cloud/iteration_N/, cameras.json, cfg_args)"""
    up: Literal["z", "-y", "y"] = "z"
    """the PLY's up axis: z (vadgs's world), -y (3DGS/COLMAP files: SuperSplat and most splat viewers
    show it upright) or y (y-up tools); z only with --inria"""
    scene: SceneOpt = None
    """the run's scene folder if it moved, checked by its fingerprint (None: where the run recorded it)"""

    def main(self) -> int:
        """Write the PLY and the sky map; 0."""
        from vadgs.train.results.export import export_world

        if self.inria and self.up != "z":
            raise ValueError(f"--up {self.up}: not with --inria (its cameras.json and source model are z up)")

        with _writing(self.run, self.out or run_dir(self.run), "vadgs export"):
            run = load_run(self.run, scene=self.scene)
            frame, _ = frame_position(_scene(run), self.frame, "--frame")
            out = Path(self.out) if self.out else run_dir(self.run) / "export" / f"frame{frame:03d}"
            if self.inria:
                _check_inria_out(out, _owner(self.run, out), run.scene_ref or {})
            owner = _check_into(self.run, out)
            res = export_world(run.model, _scene(run), frame, out, inria=self.inria, iteration=run.step,
                               scene_ref=run.scene_ref, up=self.up)  # fmt: skip
            written = [p for p in res[:5] if p is not None]
            if (out / "sparse" / "0").is_dir():
                written += [p for p in (out / "sparse" / "0").iterdir() if p.is_file()]
            record_files(owner, written)
        print(
            f"wrote {res.ply} ({res.num_gaussians} Gaussians, world at frame {frame}, {self.up} up) "
            f"and {res.sky_png}"
        )
        return 0


def _check_inria_out(out: Path, owner: Path, scene_ref: dict) -> None:
    """Refuse an INRIA export into the scene's folder, or over another model's files.

    Another model's: a ``cfg_args`` / ``cameras.json`` that vadgs did not write (not recorded).
    """
    scene = scene_ref.get("path")
    if scene:
        real, scene_real = out.resolve(), Path(scene).resolve()
        if real == scene_real or real in scene_real.parents:
            raise ValueError(
                f"--out {out}: is the run's scene folder ({scene_real}) or holds it; "
                "an INRIA export writes cameras.json, cfg_args and sparse/ there: give another folder"
            )
    mine = {p.resolve() for p in recorded_files(owner)}
    names = ("cfg_args", "cameras.json")
    theirs = [n for n in names if (out / n).exists() and (out / n).resolve() not in mine]
    if theirs:
        raise ValueError(
            f"--out {out}: holds {', '.join(theirs)} that vadgs did not write (another model's); "
            "nothing was changed: give a new or empty folder"
        )


@dataclass(frozen=True)
class ViewCommand(Command):
    """Open a run in the browser (viser): Gaussians, cars at a frame slider, camera frusta, VAD-GS additions.

    Serves ``http://HOST:PORT`` until Ctrl+C, SIGTERM (or ``--timeout`` seconds); see
    :mod:`vadgs.viewer`. ``HOST`` is 127.0.0.1 unless ``--host`` says otherwise: the viewer has no
    authentication, so listening on other interfaces (``--host 0.0.0.0``) is an explicit choice,
    printed with a warning.
    """

    run: RunArg
    """run folder (or its checkpoint.pt)"""
    host: str = "127.0.0.1"
    """interface to listen on (default this machine only; 0.0.0.0: every interface, no authentication)"""
    port: int = checked(8080, int_field(1, 65535))
    """port (the next free one if taken)"""
    frame: int | None = None
    """the scene's frame index shown first (default: its first frame)"""
    max_gaussians: int = checked(1_000_000, int_field(1))
    """send at most this many Gaussians to the browser (a random subset)"""
    timeout: float | None = checked(None, float_field(0, lo_open=True, optional=True))
    """stop serving after this many seconds (default: at Ctrl+C)"""
    scene: SceneOpt = None
    """the run's scene folder if it moved, checked by its fingerprint (None: where the run recorded it)"""

    def main(self) -> int:
        """Serve the viewer until Ctrl+C or the timeout; 0."""
        try:
            import viser
        except ImportError:
            raise ImportError("vadgs view needs viser: pip install 'vadgs[viewer]'") from None
        from vadgs.train.session import stop_on_signals
        from vadgs.viewer import build_viewer

        run = load_run(self.run, scene=self.scene)
        model, scene = run.model, _scene(run)
        _, position = frame_position(scene, self.frame, "--frame")
        stop = threading.Event()
        # SIGINT / SIGTERM stop serving (exit 0), from before the server starts: a signal that
        # arrives while the scene is sent, or just after the address is printed, is not fatal
        with stop_on_signals(stop.set, stop.is_set):
            server = viser.ViserServer(host=self.host, port=self.port, verbose=False)
            try:
                viewer = build_viewer(model, scene, server, position, max_gaussians=self.max_gaussians)
                shown = sum(int(g.rows.numel()) for g in viewer.groups)
                what = (
                    f"{len(scene.frames)} photos"
                    if scene.is_photo_collection
                    else f"{len(model.track_ids)} moving objects, {len(scene.frames)} frames"
                )
                print(f"viewing {run_dir(self.run)}: {shown} of {model.num_gaussians} Gaussians, {what}")
                print(_listening(self.host, server.get_port()), flush=True)
                deadline = None if self.timeout is None else time.monotonic() + self.timeout
                while not stop.is_set() and (deadline is None or time.monotonic() < deadline):
                    stop.wait(0.2)
            except KeyboardInterrupt:
                pass
            finally:
                server.stop()
        return 0


def _too_many(limit: int, count: object) -> str:
    """The message of a video longer than ``--max-frames``.

    Example:
        >>> _too_many(100000, 100000000)
        'expected at most 100000 frames (--max-frames raises it), got 100000000'
    """
    return f"expected at most {limit} frames (--max-frames raises it), got {count}"


def _warn_out_of_view(model, scene, traj, spec: str, sample: int = 256) -> bool:
    """Print one warning line when no Gaussian is in view of any frame of ``traj`` (True then).

    Up to ``sample`` poses, evenly spaced, are checked against the static Gaussians' centres (all
    of them on a model without static ones): ``shift:1e30`` would render only the sky.
    """
    import torch

    from vadgs.train.results.video import gaussians_in_view

    means = model.params["means"].detach()
    static = model.node_ids < 0
    means = means[static] if bool(static.any()) else means
    if means.shape[0] == 0:
        return False
    pick = torch.linspace(0, len(traj.time) - 1, min(sample, len(traj.time))).round().long().unique()
    info = scene.cameras_info[traj.camera]
    poses = traj.cam_to_world[pick]
    if int(gaussians_in_view(means, poses, info.K, info.image_size).sum()) > 0:
        return False
    centre = means.double().median(0).values
    far = float((poses[:, :3, 3].double() - centre).norm(dim=-1).min())
    print(
        f"vadgs render: warning: --trajectory {spec}: no Gaussian in view of any of its {len(traj.time)} "
        f"frames (the camera path passes {far:.3g} m from the scene's centre at the nearest); "
        "the video shows only the background",
        file=sys.stderr,
    )
    return True


def _listening(host: str, port: int) -> str:
    """The line saying where the viewer listens (a warning when that is more than this machine).

    Example:
        >>> _listening("127.0.0.1", 8080)
        'open http://127.0.0.1:8080 (listening on 127.0.0.1 only; Ctrl+C or SIGTERM stops)'
    """
    if host in ("0.0.0.0", "::", ""):
        return (
            f"open http://127.0.0.1:{port} (listening on {host or '0.0.0.0'}: EVERY network interface, "
            "without authentication; Ctrl+C or SIGTERM stops)"
        )
    shown = f"[{host}]" if ":" in host else host
    return f"open http://{shown}:{port} (listening on {host} only; Ctrl+C or SIGTERM stops)"
