"""A run as a library concept: a scene reference, a run folder, and the whole run as one call.

A run is a folder (``--out``) holding ``checkpoint.pt`` (:mod:`vadgs.train.checkpoint`),
``log.jsonl``, ``config.json``, ``metrics.json`` and the exports; its checkpoint records the
*scene reference* — ``{"kind": "benchmark" | "dgp" | "colmap", "path": ..., ...}``, by absolute
paths and a content fingerprint — that :func:`open_run_scene` reopens from any current folder
(``docs/design.md``, "A run"). One process writes a run folder at a time (:class:`RunLock`).

- Scene references (:mod:`vadgs.train.scenes`), one typed dataclass per kind:
  :class:`~vadgs.train.scenes.BenchmarkRef`, :class:`~vadgs.train.scenes.DGPRef`,
  :class:`~vadgs.train.scenes.ColmapRef`; :func:`~vadgs.train.scenes.scene_ref` picks the kind of
  a folder; :func:`~vadgs.train.scenes.prepare_scene` opens one for a new run (a distorted COLMAP
  project is undistorted into the run folder) and returns the reference the checkpoint stores.
- :func:`train_scene`: open → train → :func:`finish_run` (evaluate, export, ``metrics.json``), or
  continue a run folder's checkpoint. ``vadgs train`` and ``vadgs batch`` are adapters over it.
- :func:`load_run` reads a finished or running run back (``scene=``: the folder its scene moved
  to); :func:`~vadgs.train.checkpoint.describe_run` / :func:`~vadgs.train.checkpoint.clear_run`
  look after its folder.

Example::

    from vadgs.train.scenes import scene_ref

    ref = scene_ref("data/street_a", scale=0.5)
    outcome = train_scene(ref, TrainConfig(vad=VisibilityDensifyConfig()), "runs/street_a")
    outcome.metrics["test"]["psnr"]
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import TYPE_CHECKING, Any, NamedTuple

import torch

from vadgs.data.scene import Scene
from vadgs.io import write_json
from vadgs.runfolder import describe_files, is_vadgs_folder, record_files
from vadgs.runlock import RunLock
from vadgs.train.checkpoint import (
    CHECKPOINT_NAME,
    Checkpoint,
    check_new_run,
    load_checkpoint,
)
from vadgs.train.scenes import (
    ColmapRef,
    folder_kind,
    open_run_scene,
    prepare_scene,
)
from vadgs.train.session import reclaim_signals

if TYPE_CHECKING:
    from vadgs.train.scenes import SceneRef

__all__ = ["Run", "RunOutcome", "finish_run", "frame_position", "load_run", "train_scene"]


def finish_run(
    trainer: Any, out: str | Path, result: Any, progress: bool = True, started: float | None = None
) -> dict[str, Any]:
    """Finish a trained run: evaluate the test views, export the PLYs, write ``metrics.json``.

    Args:
        trainer: the :class:`~vadgs.train.trainer.Trainer` that ran.
        out: the run folder (``metrics.json`` and ``ply/`` go there).
        result: its :class:`~vadgs.train.loop.TrainResult`.
        progress: progress bar of the evaluation.
        started: a :func:`time.perf_counter` value: ``wall_s`` is the time since then, this
            function included.

    Returns:
        The metrics written: steps, time, memory, Gaussians (per node), threads, ``test`` (the
        :func:`~vadgs.train.results.evaluate.evaluate` metrics, when the scene has test views),
        ``vad_events`` (VAD-GS runs), ``wall_s`` (with ``started``). Written once, atomically.
    """
    from vadgs.train.results.evaluate import evaluate
    from vadgs.train.results.export import export_model

    out = Path(out)
    scene = trainer.scene
    metrics: dict[str, Any] = {
        "scene": scene.name,
        "steps": result.step,
        "completed": result.completed,
        "train_s": round(result.train_s, 1),
        "s_per_step": round(result.train_s / max(result.step, 1), 3),
        "peak_rss_mb": round(result.peak_rss_mb, 1),
        "num_gaussians": result.num_gaussians,
        "gaussians_per_node": trainer.model.node_counts(),
        "threads": torch.get_num_threads(),
    }
    if scene.test_views:
        metrics["test"] = evaluate(
            trainer.model,
            scene,
            config=trainer.config.raster,
            progress=progress,
            appearance=trainer.appearance,
        ).to_dict()
    written = export_model(trainer.model, out / "ply", [f.index for f in scene.frames])
    record_files(out, written)
    if "vad_events" in trainer.state:
        metrics["vad_events"] = trainer.state["vad_events"]
    if started is not None:
        metrics["wall_s"] = round(time.perf_counter() - started, 1)
    record_files(out, [write_json(out / "metrics.json", metrics, default=str)])
    return metrics


class Run(NamedTuple):
    """A trained run, as :func:`load_run` reads it from its checkpoint.

    Attributes:
        model: the :class:`~vadgs.train.model.GaussianModel`.
        scene: the scene it refers to, reopened (None with ``open=False``).
        config: its :class:`~vadgs.train.config.TrainConfig`.
        appearance: its :class:`~vadgs.train.appearance.AppearanceModel`, or None.
        step: steps trained.
        checkpoint: the :class:`~vadgs.train.checkpoint.Checkpoint` it was read from.
        scene_ref: the scene reference as used (:func:`open_run_scene`: the paths found, the
            fingerprint of what was opened), or None with ``open=False``.
    """

    model: Any
    scene: Scene | None
    config: Any
    appearance: Any
    step: int
    checkpoint: Checkpoint
    scene_ref: dict[str, Any] | None = None


def load_run(path: str | Path, open: bool = True, scene: str | Path | None = None) -> Run:
    """Read a run folder (or its ``checkpoint.pt``): the model, its scene, config and appearance.

    Args:
        path: the run folder or its checkpoint.
        open: reopen the scene of its scene reference (:func:`open_run_scene`: from any current
            folder; a scene whose fingerprint differs from the recorded one is refused).
        scene: the scene's folder when it moved (``--scene``); None: the recorded one.

    Raises:
        FileNotFoundError: no checkpoint, or the scene is not where the run recorded it (the
            message says where it looked and names ``--scene``).
        ValueError: from :func:`~vadgs.train.checkpoint.load_checkpoint`, or a scene that is not
            the run's (its fingerprint differs).
    """
    from vadgs.train.appearance import AppearanceModel
    from vadgs.train.model import GaussianModel

    _check_is_run(Path(path))
    ckpt = load_checkpoint(path)
    config = ckpt.train_config()
    model = GaussianModel.from_state(ckpt.model, ckpt.model_extra)
    appearance = None
    if config.appearance is not None and ckpt.appearance is not None:
        appearance = AppearanceModel.from_state_dict(ckpt.appearance["model"], config.appearance.centered)
    opened, located = None, None
    if open:
        path = Path(path)
        opened, located = open_run_scene(ckpt.scene_ref, path if path.is_dir() else path.parent, scene)
    return Run(model, opened, config, appearance, ckpt.step, ckpt, located)


def _check_is_run(path: Path) -> None:
    """Refuse a scene, a COLMAP project or a folder of photos given where a run goes, saying what it is."""
    if not path.is_dir() or (path / CHECKPOINT_NAME).is_file():
        return
    what = {"benchmark": "a benchmark scene", "colmap": "a COLMAP project"}.get(folder_kind(path) or "")
    if what is not None:
        raise FileNotFoundError(
            f"RUN {path}: is {what}, not a run (no {CHECKPOINT_NAME}): train it first, "
            f"vadgs train {path} --out RUN, then give RUN"
        )
    if (path / "metrics.json").is_file() and is_vadgs_folder(path):
        raise FileNotFoundError(
            f"RUN {path}: a finished run whose {CHECKPOINT_NAME} is missing (its metrics.json is "
            "there): the model is gone, nothing to evaluate, render or export"
        )


def frame_position(scene: Scene, frame: int | None, name: str = "frame") -> tuple[int, int]:
    """A frame index of the scene (None: its first) → ``(index, position)`` in ``scene.frames``.

    Raises:
        ValueError: naming ``name`` (e.g. ``"--frame"``), the scene's frames and the value.
    """
    indices = [f.index for f in scene.frames]
    index = indices[0] if frame is None else frame
    if index not in indices:
        raise ValueError(f"{name}: scene {scene.name!r} has frames {indices[0]}..{indices[-1]}, got {index}")
    return index, indices.index(index)


# ---------------------------------------------------------------------------------------------------
# the whole run


class RunOutcome(NamedTuple):
    """What :func:`train_scene` did.

    Attributes:
        out_dir: the run folder.
        completed: the run reached its last step (and was finished: ``metrics``).
        reason: why training stopped (:class:`~vadgs.train.loop.TrainResult`): ``"done"``,
            ``"interrupted"`` (SIGINT / SIGTERM, checkpointed) or ``"time limit"`` (``max_minutes``).
        step: steps trained.
        metrics: ``metrics.json`` as written by :func:`finish_run`, or None when not completed.
    """

    out_dir: Path
    completed: bool
    reason: str
    step: int
    metrics: dict[str, Any] | None


def train_scene(
    scene: SceneRef | None,
    config: Any = None,
    out_dir: str | Path = "outputs/run",
    *,
    resume: bool = False,
    overwrite: bool = False,
    config_changes: dict[str, Any] | None = None,
    init_points: Any = None,
    progress: bool = True,
    log: Any = None,
    scene_path: str | Path | None = None,
    scene_flag: str = "scene_path",
) -> RunOutcome:
    """A whole run as one call: open the scene, train, evaluate, export, write ``metrics.json``.

    The run folder is locked for the whole call (:class:`RunLock`): a second process writing
    into it fails at once, naming the first one's pid.

    Args:
        scene: the scene of a new run (:func:`~vadgs.train.scenes.scene_ref`); None with ``resume``.
        config: its :class:`~vadgs.train.config.TrainConfig` (default: the defaults).
        out_dir: the run folder.
        resume: continue the checkpoint in ``out_dir`` exactly; the scene and configuration are
            the checkpoint's, save ``config_changes``. The scene is found from any current folder
            and checked by its fingerprint (:func:`open_run_scene`).
        overwrite: a new run may replace a previous run in ``out_dir`` (else that is an error).
        config_changes: what a resumed run may change (:data:`~vadgs.train.checkpoint.RESUMABLE_CHANGES`).
        init_points: :class:`~vadgs.data.scene.ColmapPoints` that initialise a new run (with
            their TRACK table) besides the scene's own points, or a function of the opened scene
            that returns them (e.g. after checking that a COLMAP model matches its views).
        progress: progress bars.
        log: a ``print``-like callable for what the run does (None: silent).
        scene_path: with ``resume``: the folder the run's scene moved to (its fingerprint must
            match); the resumed run records it.
        scene_flag: how the messages name ``scene_path`` (the CLI's argument).

    Returns:
        :class:`RunOutcome`. A run stopped early (signal, ``max_minutes``) keeps its checkpoint
        and is not finished; call again with ``resume=True``.

    Raises:
        ValueError, FileNotFoundError: bad inputs, named; errors of training propagate (the
            checkpoint of the last good step stays).
        vadgs.runlock.RunInUseError: another live process writes into ``out_dir`` (its pid named).
    """
    started = time.perf_counter()
    out = Path(out_dir)
    if resume:
        if scene is not None or config is not None:
            raise ValueError("train_scene(resume=True): the scene and config are the checkpoint's; pass None")
        if not (out / CHECKPOINT_NAME).is_file():
            raise FileNotFoundError(f"resume: no checkpoint in {out}")
    else:
        if scene is None:
            raise ValueError("train_scene: give a scene reference (scene_ref(path)) or resume=True")
        if config_changes:
            raise ValueError("train_scene: config_changes are for resume=True; a new run takes config")
        if scene_path is not None:
            raise ValueError("train_scene: scene_path is for resume=True; a new run takes scene")
    with RunLock(out, "vadgs train", log=log):
        trainer = _start(scene, config, out, resume, overwrite, config_changes, init_points, progress,
                         log, scene_path, scene_flag)  # fmt: skip
        result = trainer.train()
        metrics = finish_run(trainer, out, result, progress, started) if result.completed else None
    return RunOutcome(out, bool(result.completed), str(result.reason), int(result.step), metrics)


def _start(
    scene: SceneRef | None,
    config: Any,
    out: Path,
    resume: bool,
    overwrite: bool,
    config_changes: dict[str, Any] | None,
    init_points: Any,
    progress: bool,
    log: Any,
    scene_path: str | Path | None,
    scene_flag: str,
) -> Any:
    """The :class:`~vadgs.train.trainer.Trainer` of :func:`train_scene`, new or resumed (the lock held)."""
    from vadgs.train.config import TrainConfig
    from vadgs.train.trainer import Trainer

    say = log if log is not None else (lambda *_: None)
    ckpt = load_checkpoint(out) if resume else None
    if isinstance(scene, ColmapRef) or (ckpt is not None and ckpt.scene_ref.get("kind") == "colmap"):
        import pycolmap  # noqa: F401  (now: its glog takes SIGTERM over, given back before the work)

        reclaim_signals()
    if ckpt is not None:
        opened, located = open_run_scene(ckpt.scene_ref, out, scene_path, scene_flag)
        trainer = Trainer.from_checkpoint(
            out,
            scene=opened,
            scene_ref=located,
            progress=progress,
            config_changes=config_changes or None,
            log=log,
        )
        kind = "VAD-GS" if trainer.config.vad is not None else "standard densification"
        say(f"resuming {out} at step {trainer.step}/{trainer.config.iterations} ({kind})")
        if located.get("path") != ckpt.scene_ref.get("path"):
            say(f"the run's scene is now {located['path']} (recorded: {ckpt.scene_ref.get('path')})")
        return trainer
    config = TrainConfig() if config is None else config
    # the Trainer checks these too; here before opening the scene, which may undistort into out_dir
    held, doomed = check_new_run(out, overwrite, "out_dir", "resume=True", "overwrite=True")
    if held is not None:  # shown before anything is removed, as git clean -n does
        say(f"overwrite: the previous run in {out} ({held}) is removed as training starts: "
            f"{describe_files(out, doomed)}")  # fmt: skip
    assert scene is not None  # train_scene refuses a new run without a scene
    opened, stored = prepare_scene(scene, out, say)
    if callable(init_points):
        init_points = init_points(opened)
    trainer = Trainer(
        opened,
        config,
        out_dir=out,
        scene_ref=stored,
        colmap_points=init_points,
        progress=progress,
        overwrite=overwrite,
        log=log,
    )
    n = trainer.model.num_gaussians
    say(f"{opened}: {len(opened.train_views)} training views, {n} initial Gaussians")
    return trainer
