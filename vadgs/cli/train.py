"""``vadgs train`` and ``vadgs batch``: adapters over :func:`vadgs.train.run.train_scene`.

``vadgs train`` is parsed by tyro over :class:`TrainCommand`: the run's own flags (scene, ``--out``,
``--resume``, ...) and every field of :class:`~vadgs.train.config.TrainConfig` as a flag, nested
ones dotted (``--iterations 3000``, ``--init.max-points 50000``, ``--vad.max-instances 8``,
``--strategy.max-gaussians 1000000``, ``--raster.backend torch``), as gsplat's ``simple_trainer.py``
and nerfstudio do. The flags apply over a starting configuration: the defaults, a ``--config``
JSON file, or (``--resume``) the checkpoint's; ``--vad`` and ``--appearance`` switch those parts on,
and their fields then appear as ``--vad.*`` / ``--appearance.*``. ``vadgs train --help`` lists them
all. Errors are one line, naming the flag.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import shlex
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Any

import tyro

from vadgs.checks import Checked, checked, float_field, int_field
from vadgs.cli._common import (
    Command,
    Flag,
    Positional,
    as_flag,
    check_out_dir,
    metrics_summary,
    parse_command,
    scene_arg,
)
from vadgs.train.config import TrainConfig

__all__ = [
    "SESSION_FIELDS",
    "BatchCommand",
    "TrainCommand",
    "batch_train_args",
    "parse_train",
    "resume_changes",
]


@dataclass(frozen=True)
class TrainCommand(Checked):
    """Train a model on a scene (``--resume`` continues the run in ``--out`` exactly)."""

    scene: Annotated[str | None, Positional, tyro.conf.arg(metavar="SCENE")] = None
    """scene folder: benchmark format (scene.json), a COLMAP model or project folder (sparse/0;
    detected), or DGP with --dgp; with --resume only for a run whose scene moved (the folder it
    moved to; checked by its fingerprint)"""
    out: Annotated[str, tyro.conf.arg(metavar="FOLDER")] = ""
    """run folder (checkpoints, metrics, PLY); required"""
    sample: Flag = False
    """use the bundled sample scene"""
    config: str | None = None
    """JSON file with (part of) a TrainConfig: the starting point of the flags below"""
    resume: Flag = False
    """continue the run in --out from its checkpoint (only the fields of RESUMABLE_CHANGES may change:
    --iterations, --max-minutes, --device, --threads, --checkpoint-every, --checkpoint-minutes,
    --log-every)"""
    overwrite: Flag = False
    """--out may hold a previous run: its files are removed and training starts over"""
    no_progress: Flag = False
    """no progress bar"""
    scale: float | None = checked(None, float_field(0, lo_open=True, optional=True))
    """image resolution factor (default: the working resolution, the largest 1/2^k that brings the
    longest image side to <= 1024 px; 0.5 for a rendered benchmark scene, 240x144 for street_a)"""
    dgp: Flag = False
    """SCENE is a DGP scene folder"""
    cameras: str | None = None
    """DGP: comma-separated camera names"""
    test_frames: tuple[int, ...] = ()
    """DGP: held-out frames (samples)"""
    colmap_scene: Flag = False
    """SCENE is a COLMAP model or project folder (detected without it when there is no scene.json)"""
    images: str | None = None
    """COLMAP scene: the images folder (default: images/ next to the model)"""
    test_every: int | None = checked(None, int_field(0, optional=True))
    """COLMAP scene: hold out every N-th image in name order, index % N == 0 (default 8; 0 = none)"""
    no_normalize: Flag = False
    """COLMAP scene: keep COLMAP's frame and scale (default: cameras centred, up +z, median
    camera-to-point depth 10)"""
    colmap: str | None = None
    """COLMAP model of this scene's views (same image names, same world frame) whose points are added
    to the initialisation"""
    vad: Flag = False
    """VAD-GS visibility-aware densification (the paper); its settings are then --vad.*"""
    appearance: Flag = False
    """learn a colour transform per camera (real rigs with differently exposed cameras); its settings
    are then --appearance.*"""
    debug: Flag = False
    """show the traceback of an error"""
    train: Annotated[TrainConfig, tyro.conf.arg(name="")] = field(default_factory=TrainConfig)

    @classmethod
    def parse(cls, argv: list[str], prog: str = "vadgs train") -> TrainCommand | None:
        """:func:`parse_train` (the flags apply over the defaults, ``--config`` or the checkpoint)."""
        return parse_train(argv)

    def main(self) -> int:
        """Train (or resume) the run in ``--out``; 0, or 130 when interrupted."""
        from vadgs.runlock import RunLock
        from vadgs.train.checkpoint import CHECKPOINT_NAME, check_new_run
        from vadgs.train.run import train_scene

        out = check_out_dir(self.out, create=False)
        RunLock.check_free(out)  # before the checks below: a run in use is named by its pid
        progress = not self.no_progress
        if self.resume:
            if not (out / CHECKPOINT_NAME).is_file():
                raise FileNotFoundError(f"--resume: no checkpoint in {out}")
            changes = resume_changes(self, out)
            outcome = train_scene(
                None, None, out, resume=True, config_changes=changes, progress=progress, log=print,
                scene_path=self.scene, scene_flag="SCENE (the folder the scene moved to)",
            )  # fmt: skip
        else:
            if self.scene is None and not self.sample:
                raise ValueError("train: give a SCENE folder (or --sample for the bundled sample)")
            # a folder vadgs did not write, with or without --overwrite; a manifest entry outside
            # the run, a symlinked ply/, a read-only folder: refused before any work
            check_new_run(out, self.overwrite)
            scene = _scene(self)
            outcome = train_scene(
                scene,
                self.train,
                out,
                overwrite=self.overwrite,
                init_points=_init_points(self, scene.scale),
                progress=progress,
                log=print,
            )
        if not outcome.completed:
            print(f"stopped ({outcome.reason}) at step {outcome.step}; checkpoint {out / CHECKPOINT_NAME}; "
                  f"continue with: vadgs train --out {out} --resume")  # fmt: skip
            return 130 if outcome.reason == "interrupted" else 0
        assert outcome.metrics is not None  # written for a completed run
        print(metrics_summary(outcome.metrics))
        print(f"wrote {out / 'metrics.json'}, {out / 'ply'}")
        return 0


# TrainCommand fields of the session, not of the run (the others are refused on --resume)
SESSION_FIELDS = ("scene", "out", "resume", "no_progress", "debug", "train")  # SCENE: where it moved


def _read_config_file(path: str) -> tuple[dict, TrainConfig]:
    """A ``--config`` JSON file and its :class:`TrainConfig`, type-checked against it on its own."""
    from vadgs.config import config_from_dict

    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"--config {p}: no such file")
    try:
        data = json.loads(p.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise ValueError(f"--config {p}: not valid JSON ({e})") from None
    except RecursionError:
        raise ValueError(f"--config {p}: nested too deeply to parse (over ~1000 levels)") from None
    return data, config_from_dict(TrainConfig, data, where=f"--config {p}")


def _starting_config(argv: list[str]) -> tuple[TrainConfig, dict]:
    """The configuration the flags apply over, and the ``--config`` file's dict (``{}`` without).

    The defaults, the ``--config`` file, or with ``--resume`` the checkpoint's; ``--vad`` and
    ``--appearance`` switch those parts on.
    """
    from vadgs.train.appearance import AppearanceConfig
    from vadgs.train.checkpoint import CHECKPOINT_NAME, load_checkpoint
    from vadgs.train.vad import VisibilityDensifyConfig

    pre = argparse.ArgumentParser(add_help=False, allow_abbrev=False)
    for name in ("--config", "--out"):
        pre.add_argument(name)
    for name in ("--resume", "--vad", "--appearance"):
        pre.add_argument(name, action="store_true")
    known, _ = pre.parse_known_args(argv)
    data: dict = {}
    if known.resume and known.out:
        out = Path(known.out)
        if not (out / CHECKPOINT_NAME).is_file():
            raise FileNotFoundError(f"--resume: no checkpoint in {out}")
        base = load_checkpoint(out).train_config()
    elif known.config:
        data, base = _read_config_file(known.config)
    else:
        base = TrainConfig()
    if known.vad and base.vad is None:
        base = dataclasses.replace(base, vad=VisibilityDensifyConfig())
    if known.appearance and base.appearance is None:
        base = dataclasses.replace(base, appearance=AppearanceConfig())
    return base, data


def parse_train(argv: list[str]) -> TrainCommand | None:
    """``vadgs train``'s arguments → :class:`TrainCommand` (None after ``--help``, which it prints).

    Raises:
        ValueError: a bad flag or value, as one line naming the flag.
    """
    argv = list(argv)
    if "-h" in argv or "--help" in argv:  # the help shows the defaults of the starting config
        base, _ = _starting_config([a for a in argv if a not in ("-h", "--help", "--resume")])
        return parse_command(TrainCommand, ["--help"], "vadgs train", default=TrainCommand(train=base))
    base, data = _starting_config(argv)
    cmd = parse_command(TrainCommand, argv, "vadgs train", default=TrainCommand(train=base))
    assert cmd is not None  # not --help
    if not cmd.out:
        raise ValueError("--out: required (the run folder)")
    backend_given = any(a.startswith("--raster.backend") for a in argv) or "backend" in (
        data.get("raster") or {}
    )
    if not cmd.resume:
        cmd = dataclasses.replace(cmd, train=_short_run_schedule(cmd.train, argv, data))
    if str(cmd.train.device).startswith("cuda") and not backend_given and not cmd.resume:
        raster = dataclasses.replace(cmd.train.raster, backend="gsplat")  # gsplat's CUDA rasterizer on GPUs
        cmd = dataclasses.replace(cmd, train=dataclasses.replace(cmd.train, raster=raster))
    return cmd


def _short_run_schedule(config: TrainConfig, argv: list[str], data: dict) -> TrainConfig:
    """The schedule of a run shorter than the defaults' 3000 steps, scaled to ``--iterations``.

    :func:`~vadgs.train.config.scale_schedule` (gsplat's ``steps_scaler``), said in one line;
    unless a flag or the ``--config`` file sets one of its step counts: the schedule is then the
    caller's, as given.
    """
    from vadgs.train.config import SCHEDULE_FIELDS, SCHEDULE_ITERATIONS, scale_schedule

    given_flags = {a.split("=")[0].replace("_", "-") for a in argv if a.startswith("--")}
    flags = {f"--strategy.{k.replace('_', '-')}" for k in SCHEDULE_FIELDS} | {"--sh-degree-interval"}
    in_file = set(data.get("strategy") or {}) & set(SCHEDULE_FIELDS) or "sh_degree_interval" in data
    if given_flags & flags or in_file:
        return config
    out = scale_schedule(config)
    if out != config:
        s, f = out.strategy, config.iterations / SCHEDULE_ITERATIONS
        print(
            f"short run: the schedule follows --iterations {config.iterations} (x{f:.3g} of "
            f"{SCHEDULE_ITERATIONS}): densify from step {s.refine_start_iter} every {s.refine_every} "
            f"steps, opacity reset every {s.reset_every or 'never'}, SH degree up every "
            f"{out.sh_degree_interval} steps (--strategy.refine-start-iter, --strategy.refine-every, "
            "... set them)"
        )
    return out


def _flat(d: dict, prefix: str = "") -> dict[str, Any]:
    out: dict[str, Any] = {}
    for k, v in d.items():
        if isinstance(v, dict):
            out.update(_flat(v, f"{prefix}{k}."))
        else:
            out[f"{prefix}{k}"] = v
    return out


def resume_changes(cmd: TrainCommand, out: Path) -> dict:
    """The configuration changes ``--resume`` can honour (said aloud); anything else is refused."""
    from vadgs.train.checkpoint import RESUMABLE_CHANGES, load_checkpoint

    stored = load_checkpoint(out)
    before, step = stored.train_config(), stored.step
    da, db = before.to_dict(), cmd.train.to_dict()
    # a part switched on or off (vad, appearance) is one change, not one per field
    switched = sorted(k for k in da.keys() | db.keys() if (da.get(k) is None) != (db.get(k) is None))
    a = _flat({k: v for k, v in da.items() if k not in switched})
    b = _flat({k: v for k, v in db.items() if k not in switched})
    changed = switched + sorted(k for k in a.keys() | b.keys() if a.get(k) != b.get(k))
    defaults = TrainCommand()
    given = [
        "SCENE" if f.name == "scene" else as_flag(f.name)
        for f in dataclasses.fields(TrainCommand)
        if f.name not in SESSION_FIELDS and getattr(cmd, f.name) != getattr(defaults, f.name)
    ]
    refused = list(dict.fromkeys(given + [as_flag(k) for k in changed if k not in RESUMABLE_CHANGES]))
    if refused:
        allowed = ", ".join(as_flag(k) for k in RESUMABLE_CHANGES)
        raise ValueError(
            f"--resume: {', '.join(refused)} cannot be honoured: a resumed run keeps the scene and "
            f"configuration of its checkpoint (only {allowed} can change); start a new run with "
            "--overwrite instead"
        )
    changes = {k: b[k] for k in changed}
    if "iterations" in changes:
        if changes["iterations"] < step:
            raise ValueError(
                f"--resume --iterations {changes['iterations']}: the run is already at step {step}"
            )
        print(
            f"NOTE: --iterations changes the run from {a['iterations']} to {changes['iterations']} "
            "steps; the means' learning-rate decay and VAD-GS's event window "
            "(last_event_fraction) follow the new total from here on, so the result differs "
            "from a run trained with either total from the start"
        )
    for key in changes:
        if key != "iterations":
            print(f"NOTE: {as_flag(key)} changes {key} from {a.get(key)!r} to {changes[key]!r}")
    return changes


def _scene(cmd: TrainCommand) -> Any:
    """The typed reference of ``vadgs train``'s SCENE (benchmark, dgp, colmap), checking each kind's flags.

    A COLMAP model or project folder without ``scene.json`` is detected without ``--colmap-scene``
    (:func:`vadgs.train.scenes.scene_ref`).
    """
    from vadgs.train.scenes import scene_ref

    if cmd.dgp and cmd.colmap_scene:
        raise ValueError("--dgp, --colmap-scene: give one scene kind")
    path = scene_arg(cmd.scene)
    kind = "dgp" if cmd.dgp else "colmap" if cmd.colmap_scene else None
    if kind is None and cmd.scene is not None:
        kind = scene_ref(path).kind
    kind = kind or "benchmark"
    if kind != "colmap":
        for key, flag in (
            ("images", "--images"),
            ("test_every", "--test-every"),
            ("no_normalize", "--no-normalize"),
        ):
            if getattr(cmd, key) not in (None, False):
                raise ValueError(
                    f"{flag}: only for a COLMAP scene (SCENE a COLMAP model or project folder), "
                    f"got a {kind} scene {path}"
                )
    elif cmd.colmap:
        raise ValueError("--colmap: not with a COLMAP scene, whose own SfM points initialise it")
    elif cmd.cameras or cmd.test_frames:
        raise ValueError("--cameras / --test-frames: DGP only; a COLMAP scene's split is --test-every")
    # the working resolution (photos to a longest side <= 1024 px), or the pixel size at --scale
    from vadgs.data.resolution import working_resolution

    cameras = cmd.cameras.split(",") if (kind == "dgp" and cmd.cameras) else None
    if cmd.scale is None:
        chosen = working_resolution(path, kind, cameras)
    else:  # only the line: a scene whose metadata cannot say is reported by its loader, by field
        try:
            chosen = working_resolution(path, kind, cameras, scale=cmd.scale)
        except (ValueError, KeyError, TypeError, OSError):
            chosen = None
    if chosen is not None:
        print(chosen.describe())
    scale = cmd.scale if chosen is None else chosen.scale
    if kind == "colmap":
        test_every = 8 if cmd.test_every is None else cmd.test_every
        return scene_ref(path, kind, images=cmd.images, scale=scale, test_every=test_every,
                         normalize=not cmd.no_normalize)  # fmt: skip
    if kind == "dgp":
        cameras = cmd.cameras.split(",") if cmd.cameras else None
        return scene_ref(path, kind, scale=scale, cameras=cameras, test_frames=cmd.test_frames)
    return scene_ref(path, kind, scale=scale)


def _init_points(cmd: TrainCommand, scale: float) -> Any:
    """``--colmap``: the SfM points of a COLMAP model of the scene's views, or None.

    A function of the opened scene, which checks that the model's images are its views.
    """
    if not cmd.colmap:
        return None
    from vadgs.data import find_colmap_model, load_colmap, match_colmap_views

    model = find_colmap_model(cmd.colmap)
    if model is None:
        raise FileNotFoundError(
            f"--colmap {cmd.colmap}: no COLMAP model (cameras, images, points3D as .bin or "
            ".txt in it, in sparse/0, sparse or 0)"
        )

    def points(scene: Any) -> Any:
        match_colmap_views(scene, model, "--colmap")
        return load_colmap(model, scale=scale, check_files=False).points

    return points


# ---------------------------------------------------------------------------------------------------
# batch


def batch_train_args(text: str) -> tuple[TrainConfig, str | None, dict]:
    """``vadgs batch --train-args``: the TrainConfig, scene kind and scene options they give.

    Parsed once, in the driver, with ``vadgs train``'s own flags, so a bad argument fails the
    batch before any scene starts; the flags of one run folder (``--out``, ``--resume``, ...) are
    refused.
    """
    words = shlex.split(text)
    for word in ("--out", "--resume", "--overwrite", "--sample", "--colmap", "-h", "--help"):
        if word in words or any(w.startswith(word + "=") for w in words):
            raise ValueError(
                f"--train-args: {word} is not for a batch (the scenes and run folders are its own)"
            )
    cmd = parse_train(["--out", ".", *words])
    assert cmd is not None  # no --help
    if cmd.scene is not None:
        raise ValueError(f"--train-args: SCENE {cmd.scene!r} is not for a batch (the scenes are its own)")
    if cmd.dgp and cmd.colmap_scene:
        raise ValueError("--train-args: --dgp, --colmap-scene: give one scene kind")
    kind = "dgp" if cmd.dgp else "colmap" if cmd.colmap_scene else None
    options: dict = {}
    for key in ("scale", "images", "test_every"):
        if getattr(cmd, key) is not None:
            options[key] = getattr(cmd, key)
    if cmd.no_normalize:
        options["normalize"] = False
    if cmd.cameras:
        options["cameras"] = cmd.cameras.split(",")
    if cmd.test_frames:
        options["test_frames"] = list(cmd.test_frames)
    return cmd.train, kind, options


@dataclass(frozen=True)
class BatchCommand(Command):
    """Train many scenes on Ray, one task each, retried and resumed on failure (needs vadgs[ray]).

    ``--threads`` is each run's torch threads (0: ``--cpus-per-scene``).
    """

    scenes: Annotated[tuple[str, ...], Positional, tyro.conf.arg(metavar="SCENE...")]
    """scene folders (one run folder each)"""
    out: str
    """batch folder: run folders, summary.json, summary.md"""
    address: str | None = None
    """Ray cluster: auto, ray://HEAD:10001 or HOST:6379 (default: start a local Ray)"""
    cpus_per_scene: float = checked(1.0, float_field(0, lo_open=True))
    """Ray CPUs per task"""
    gpus_per_scene: float = checked(0.0, float_field(0))
    """Ray GPUs per task"""
    max_retries: int = checked(3, int_field(0))
    """retries of a task whose worker/node died"""
    train_args: str = ""
    """arguments of each vadgs train, e.g. --train-args="--vad --iterations 3000" (with "=")"""
    no_progress: Flag = False
    """no line per finished run"""

    def __post_init__(self) -> None:
        super().__post_init__()
        if not self.scenes:
            raise ValueError("SCENE: expected at least one scene folder, got none")

    def main(self) -> int:
        """Run the batch; 0 when every run succeeded, else 1."""
        from vadgs.batch import BatchConfig, check_batch_folder, run_batch

        check_batch_folder(self.out, "--out")
        train_config, kind, options = batch_train_args(self.train_args)
        shared = {k: getattr(self, k) for k in ("address", "cpus_per_scene", "gpus_per_scene", "threads")}
        config = BatchConfig(**shared, max_retries=self.max_retries, train=train_config, scene_kind=kind,
                             scene_options=options, progress=not self.no_progress)  # fmt: skip
        try:
            summary = run_batch(list(self.scenes), self.out, config)
        except ImportError as e:
            print(f"vadgs batch: error: {e}", file=sys.stderr)
            return 2
        print(summary.to_markdown())
        print(f"wrote {Path(summary.out_dir) / 'summary.json'}, {Path(summary.out_dir) / 'summary.md'}")
        return 1 if summary.failed else 0
