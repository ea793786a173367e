"""A run folder and the scene it refers to: :func:`open_scene`, :func:`describe_run`, :func:`clear_run`.

A run is a folder (``--out``) holding ``checkpoint.pt`` (:mod:`vadgs.train.checkpoint`),
``log.jsonl``, ``config.json``, ``metrics.json`` and the exports; its checkpoint records the
*scene reference* — ``{"kind": "benchmark" | "dgp" | "colmap", "path": ..., ...}`` — that
:func:`open_scene` reopens (``docs/design.md``, "A run").
"""

from __future__ import annotations

import shutil
import time
import warnings
from pathlib import Path
from typing import Any, NamedTuple

import torch

from vadgs.data.scene import Scene
from vadgs.io import write_json
from vadgs.train.checkpoint import CHECKPOINT_NAME, _remove_stale_tmp, load_checkpoint

__all__ = ["Run", "clear_run", "describe_run", "finish_run", "frame_position", "load_run", "open_scene"]

_RUN_FILES = (CHECKPOINT_NAME, "log.jsonl", "config.json", "metrics.json", "eval.json")
_RUN_DIRS = ("ply", "renders")


def describe_run(folder: str | Path) -> str | None:
    """What run a folder holds: ``"step S/N"`` (its checkpoint), ``"finished"``, or None.

    A folder holds a run when it has a ``checkpoint.pt`` or a ``metrics.json``; a folder with only
    the log of a run killed before its first checkpoint holds nothing that can be continued.
    """
    folder = Path(folder)
    ck = folder / CHECKPOINT_NAME
    if ck.is_file():
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                c = load_checkpoint(ck)
            return f"step {int(c['step'])}/{int(c['config'].get('iterations', 0))}"
        except (ValueError, OSError) as e:
            return f"an unreadable checkpoint: {e}"
    if (folder / "metrics.json").is_file():
        return "finished, no checkpoint"
    return None


def clear_run(folder: str | Path) -> list[Path]:
    """Remove a run's files from its folder (checkpoint, log, config, metrics, eval, ply/, renders/)."""
    folder = Path(folder)
    removed = []
    for name in _RUN_FILES:
        p = folder / name
        if p.is_file():
            p.unlink()
            removed.append(p)
    for name in _RUN_DIRS:
        p = folder / name
        if p.is_dir():
            shutil.rmtree(p)
            removed.append(p)
    removed += _remove_stale_tmp(folder)
    return removed


def open_scene(ref: dict[str, Any]) -> Scene:
    """Load the scene a run refers to: ``{"kind": "benchmark" | "dgp" | "colmap", "path": ..., ...}``.

    ``dgp`` references may carry ``cameras`` and ``test_frames``. ``colmap`` references are the
    recipe of :func:`vadgs.data.colmap.open_colmap_project`, reopened by
    :func:`~vadgs.data.colmap.reopen_colmap_project`: ``path`` (the model used, the
    undistorted copy in the run folder if the input was distorted), ``images``, ``test_every``
    and ``transform`` (the normalising similarity, re-applied as recorded; None: COLMAP's frame).
    """
    from vadgs.data import load_dgp, load_scene, reopen_colmap_project

    kind = ref.get("kind", "benchmark")
    if kind == "colmap":
        return reopen_colmap_project(ref).scene
    if kind == "benchmark":
        return load_scene(ref["path"], scale=float(ref.get("scale", 1.0)))
    if kind == "dgp":
        return load_dgp(
            ref["path"],
            cameras=ref.get("cameras"),
            scale=float(ref.get("scale", 1.0)),
            test_frames=tuple(ref.get("test_frames", ())),
        )
    raise ValueError(f"scene reference: unknown kind {kind!r}")


def finish_run(
    trainer: Any, out: str | Path, result: Any, progress: bool = True, started: float | None = None
) -> dict[str, Any]:
    """Finish a trained run: evaluate the test views, export the PLYs, write ``metrics.json``.

    Args:
        trainer: the :class:`~vadgs.train.trainer.Trainer` that ran.
        out: the run folder (``metrics.json`` and ``ply/`` go there).
        result: its :class:`~vadgs.train.trainer.TrainResult`.
        progress: progress bar of the evaluation.
        started: a :func:`time.perf_counter` value: ``wall_s`` is the time since then, this
            function included.

    Returns:
        The metrics written: steps, time, memory, Gaussians (per node), threads, ``test`` (the
        :func:`~vadgs.train.evaluate.evaluate` metrics, when the scene has test views),
        ``vad_events`` (VAD-GS runs), ``wall_s`` (with ``started``). Written once, atomically.
    """
    from vadgs.train.evaluate import evaluate
    from vadgs.train.export import export_model

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
    export_model(trainer.model, out / "ply", [f.index for f in scene.frames])
    if "vad_events" in trainer.state:
        metrics["vad_events"] = trainer.state["vad_events"]
    if started is not None:
        metrics["wall_s"] = round(time.perf_counter() - started, 1)
    write_json(out / "metrics.json", metrics, default=str)
    return metrics


class Run(NamedTuple):
    """A trained run, as :func:`load_run` reads it from its checkpoint.

    Attributes:
        model: the :class:`~vadgs.train.model.GaussianModel`.
        scene: the scene it refers to, reopened (None with ``open=False``).
        config: its :class:`~vadgs.train.config.TrainConfig`.
        appearance: its :class:`~vadgs.train.appearance.AppearanceModel`, or None.
        step: steps trained.
        checkpoint: the checkpoint dict (:func:`~vadgs.train.checkpoint.load_checkpoint`).
    """

    model: Any
    scene: Scene | None
    config: Any
    appearance: Any
    step: int
    checkpoint: dict[str, Any]


def load_run(path: str | Path, open: bool = True) -> Run:
    """Read a run folder (or its ``checkpoint.pt``): the model, its scene, config and appearance.

    Args:
        path: the run folder or its checkpoint.
        open: reopen the scene of its scene reference (:func:`open_scene`).

    Raises:
        FileNotFoundError, ValueError: from :func:`~vadgs.train.checkpoint.load_checkpoint`.
    """
    from vadgs.train.appearance import AppearanceModel
    from vadgs.train.config import TrainConfig
    from vadgs.train.model import GaussianModel

    ckpt = load_checkpoint(path)
    config = TrainConfig.from_dict(ckpt["config"])
    model = GaussianModel.from_state(ckpt["model"], ckpt["model_extra"])
    appearance = None
    if config.appearance is not None and "appearance" in ckpt:
        appearance = AppearanceModel.from_state_dict(ckpt["appearance"]["model"], config.appearance.centered)
    scene = open_scene(ckpt["scene_ref"]) if open else None
    return Run(model, scene, config, appearance, int(ckpt["step"]), ckpt)


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
