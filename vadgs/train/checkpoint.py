"""Checkpoints of a run: the file, its checksum, atomic saving, loading, and what a resume may change.

A checkpoint is one ``torch.save`` file (``checkpoint.pt`` in the run folder) of plain tensors and
containers (read with ``weights_only``), with a format name, a format version
(:data:`CHECKPOINT_VERSION`) and a SHA-256 checksum of its content. A checkpoint of another format
version is refused in one line: the run must be trained again (vadgs keeps no reader of older
files). In memory it is a :class:`Checkpoint`: :func:`save_checkpoint` writes one atomically,
:func:`load_checkpoint` reads and verifies one, :func:`resumed_config` applies the changes a
resume may make (:data:`RESUMABLE_CHANGES`). :class:`~vadgs.train.trainer.Trainer` builds them
(:meth:`~vadgs.train.trainer.Trainer.checkpoint`) and continues from them
(:meth:`~vadgs.train.trainer.Trainer.from_checkpoint`). :func:`describe_run` says what run a folder
holds; :func:`clear_run` removes one.
"""

from __future__ import annotations

import errno
import hashlib
import os
import random
import shutil
from pathlib import Path
from typing import Any, NamedTuple

import torch

from vadgs.io import atomic_write, remove_stale_tmp
from vadgs.train.config import TrainConfig

__all__ = [
    "CHECKPOINT_NAME",
    "CHECKPOINT_VERSION",
    "RESUMABLE_CHANGES",
    "RUN_FILES",
    "Checkpoint",
    "StepSnapshot",
    "capture_rng",
    "check_new_run",
    "checkpoint_checksum",
    "clear_run",
    "describe_run",
    "held_run_message",
    "is_checkpoint_content",
    "load_checkpoint",
    "remove_run_tmp",
    "restore_rng",
    "resumed_config",
    "save_checkpoint",
]

CHECKPOINT_NAME = "checkpoint.pt"
_FORMAT = "vadgs-train-checkpoint"  # what makes a checkpoint.pt vadgs's
CHECKPOINT_VERSION = 2
"""The format version of the checkpoints this vadgs writes and reads (2: issue 50, nothing older read)."""
_REQUIRED = (
    "step", "config", "scene_ref", "model", "model_extra", "optimizer", "strategy_state", "sampler",
    "rng", "train_s", "checksum",
)  # fmt: skip


class StepSnapshot(NamedTuple):
    """What a training step consumes before it changes the parameters (``Trainer.snapshot``).

    Attributes:
        sampler: the view sampler's ``state_dict``.
        rng: the generators' states (:func:`capture_rng`).
    """

    sampler: dict[str, Any]
    rng: dict[str, Any]


class Checkpoint(NamedTuple):
    """A run's whole state at a step: what ``checkpoint.pt`` holds.

    Attributes:
        step: steps done.
        config: the run's :class:`~vadgs.train.config.TrainConfig` as a dict (:meth:`train_config`).
        scene_ref: how to reopen the scene (:func:`~vadgs.train.scenes.open_scene`); ``{}`` when
            the run was trained on an in-memory scene.
        model, model_extra: :meth:`GaussianModel.state_dict` and :meth:`GaussianModel.extra_state`.
        optimizer: Adam's state dict.
        strategy_state: the densification strategy's state.
        sampler: the view sampler's state.
        rng: every random generator (:func:`capture_rng`).
        train_s: training seconds so far, all sessions together.
        appearance: ``{"model", "optimizer"}`` state dicts of the appearance model, or None.
    """

    step: int
    config: dict[str, Any]
    scene_ref: dict[str, Any]
    model: dict[str, Any]
    model_extra: dict[str, Any]
    optimizer: dict[str, Any]
    strategy_state: dict[str, Any]
    sampler: dict[str, Any]
    rng: dict[str, Any]
    train_s: float = 0.0
    appearance: dict[str, Any] | None = None

    def train_config(self) -> TrainConfig:
        """The run's :class:`~vadgs.train.config.TrainConfig`."""
        return TrainConfig.from_dict(self.config)

    def to_dict(self, checksum: bool = True) -> dict[str, Any]:
        """The file's content: format, version, the fields (no ``appearance`` when None), checksum."""
        out: dict[str, Any] = {"format": _FORMAT, "version": CHECKPOINT_VERSION, **self._asdict()}
        if self.appearance is None:
            del out["appearance"]
        if checksum:
            out["checksum"] = checkpoint_checksum(out)
        return out


def capture_rng(generator: torch.Generator) -> dict[str, Any]:
    """The state of torch's global generator, ``generator`` and Python's ``random`` (plain data)."""
    st = random.getstate()
    return {
        "torch": torch.get_rng_state(),
        "generator": generator.get_state(),
        "python": [st[0], list(st[1]), st[2]],
    }


def restore_rng(rng: dict[str, Any], generator: torch.Generator) -> None:
    """Put back what :func:`capture_rng` took (``generator`` is set in place)."""
    torch.set_rng_state(rng["torch"])
    generator.set_state(rng["generator"])
    st = rng["python"]
    random.setstate((int(st[0]), tuple(int(x) for x in st[1]), st[2]))


def _hash_into(h: Any, obj: Any) -> None:
    """Feed a nested checkpoint structure into a hash, deterministically (tensors by their bytes)."""
    if isinstance(obj, torch.Tensor):
        t = obj.detach().to("cpu").contiguous()
        h.update(f"T{t.dtype}{tuple(t.shape)}".encode())
        if t.numel():
            h.update(t.reshape(-1).view(torch.uint8).numpy().tobytes())
    elif isinstance(obj, dict):
        h.update(b"{")
        for k in sorted(obj, key=repr):
            h.update(repr(k).encode())
            _hash_into(h, obj[k])
        h.update(b"}")
    elif isinstance(obj, (list, tuple)):
        h.update(b"[")
        for x in obj:
            _hash_into(h, x)
        h.update(b"]")
    else:
        h.update(repr(obj).encode())


def checkpoint_checksum(ckpt: dict[str, Any]) -> str:
    """SHA-256 of a checkpoint's content (every entry but ``checksum``; tensors by their bytes)."""
    h = hashlib.sha256()
    _hash_into(h, {k: v for k, v in ckpt.items() if k != "checksum"})
    return h.hexdigest()


def _atomic_save(obj: Any, path: Path) -> None:
    """``torch.save`` to ``path.tmp``, fsync, rename; on failure the tmp is removed, ``path`` kept.

    Raises:
        OSError: naming ``path``, in one line (disk full: ``No space left on device``).
    """
    try:
        atomic_write(path, lambda tmp: torch.save(obj, tmp))
    except BaseException as e:
        if not isinstance(e, Exception):
            raise
        kept = "the previous file is kept" if path.is_file() else "nothing was written"
        if isinstance(e, OSError) and e.errno is not None:
            code, why = e.errno, e.strerror or str(e)
        else:  # torch's zip writer reports a full disk as RuntimeError("[enforce fail at ...")
            # the partial file is already removed: compare the free space with what was to be written
            free, needed = shutil.disk_usage(path.parent).free, _tensor_bytes(obj)
            code = errno.ENOSPC if free < needed + (1 << 20) else errno.EIO
            if code == errno.ENOSPC:
                mb = f"about {needed / 2**20:.0f} MB to write, {free / 2**20:.0f} MB free"
                why = f"{os.strerror(code)}: {mb}"
            else:
                why = "write failed: " + " ".join(str(e).split())[:200]
        raise OSError(code, f"cannot write ({why}); {kept}", str(path)) from e


def _tensor_bytes(obj: Any) -> int:
    """The bytes of the tensors in a nested dict / list (what ``torch.save`` writes, roughly)."""
    if isinstance(obj, torch.Tensor):
        return obj.numel() * obj.element_size()
    if isinstance(obj, dict):
        return sum(_tensor_bytes(v) for v in obj.values())
    if isinstance(obj, (list, tuple)):
        return sum(_tensor_bytes(v) for v in obj)
    return 0


def remove_run_tmp(folder: Path) -> list[Path]:
    """Remove temporary files a killed run left behind (of checkpoints, JSON files and exports)."""
    return remove_stale_tmp(folder, "ply")


def save_checkpoint(ckpt: Checkpoint, path: str | Path) -> Path:
    """Write a checkpoint atomically (temporary file, fsync, rename), with its checksum.

    Raises:
        OSError: naming the file when it cannot be written (disk full...): the temporary file
            is removed and the previous checkpoint is left as it was.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    _atomic_save(ckpt.to_dict(), path)
    return path


def is_checkpoint_content(data: Any) -> bool:
    """Whether ``data`` (what ``torch.load`` returned) is a vadgs training checkpoint: its format marker.

    Example:
        >>> is_checkpoint_content({"format": "vadgs-train-checkpoint", "version": 2})
        True
        >>> is_checkpoint_content({"epoch": 3, "state_dict": {}})
        False
    """
    return isinstance(data, dict) and data.get("format") == _FORMAT


def load_checkpoint(path: str | Path) -> Checkpoint:
    """Read a checkpoint written by :func:`save_checkpoint` (``weights_only`` unpickling).

    Raises:
        FileNotFoundError: if it does not exist.
        ValueError: if it is corrupt, truncated, modified (its SHA-256 checksum does not match),
            not a vadgs training checkpoint, or of another format version than
            :data:`CHECKPOINT_VERSION` (one line: the file, the version found, the one read, and
            that the run must be trained again).
    """
    path = Path(path)
    if path.is_dir():
        path = path / CHECKPOINT_NAME
    if not path.is_file():
        raise FileNotFoundError(f"no checkpoint at {path}")
    try:
        ckpt = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:
        raise ValueError(f"checkpoint {path} is corrupt or unreadable ({type(e).__name__}: {e})") from None
    if not is_checkpoint_content(ckpt):
        raise ValueError(f"checkpoint {path}: not a vadgs training checkpoint")
    if ckpt.get("version") != CHECKPOINT_VERSION:
        raise ValueError(
            f"{path}: format version {ckpt.get('version')}, this vadgs reads version "
            f"{CHECKPOINT_VERSION}: train the run again"
        )
    missing = [k for k in _REQUIRED if k not in ckpt]
    if missing:
        raise ValueError(f"checkpoint {path}: missing entries {missing}")
    if checkpoint_checksum(ckpt) != ckpt["checksum"]:
        raise ValueError(f"checkpoint {path}: checksum mismatch: the file was modified or is corrupt")
    return Checkpoint(
        step=int(ckpt["step"]),
        train_s=float(ckpt["train_s"]),
        appearance=ckpt.get("appearance"),
        **{k: ckpt[k] for k in _REQUIRED if k not in ("step", "train_s", "checksum")},
    )


RESUMABLE_CHANGES = (
    "iterations",
    "max_minutes",
    "cache_gb",
    "device",
    "threads",
    "checkpoint_every",
    "checkpoint_minutes",
    "log_every",
)
"""The :class:`TrainConfig` fields :meth:`Trainer.from_checkpoint` can change (the others define the run)."""


def resumed_config(ckpt: Checkpoint, changes: dict[str, Any] | None = None) -> TrainConfig:
    """The configuration a resumed run continues with: the checkpoint's, with ``changes``.

    Raises:
        ValueError: on a field outside :data:`RESUMABLE_CHANGES`, or ``iterations`` below the
            checkpoint's step.
    """
    config = ckpt.train_config()
    if not changes:
        return config
    bad = sorted(set(changes) - set(RESUMABLE_CHANGES))
    if bad:
        raise ValueError(
            f"resume: cannot change {bad} of a run (its configuration is fixed by the "
            f"checkpoint); resumable changes: {list(RESUMABLE_CHANGES)}"
        )
    it = changes.get("iterations")
    if it is not None and int(it) < ckpt.step:
        raise ValueError(f"resume: iterations={it} is below the checkpoint's step {ckpt.step}")
    return config.replace(**changes)


# ---------------------------------------------------------------------------------------------------
# the run folder


def describe_run(folder: str | Path) -> str | None:
    """What run a folder holds: ``"step S/N"`` (its checkpoint), ``"finished"``, or None.

    A folder holds a run when it has a ``checkpoint.pt`` or a ``metrics.json``; a folder with only
    the log of a run killed before its first checkpoint holds nothing that can be continued.
    """
    folder = Path(folder)
    ck = folder / CHECKPOINT_NAME
    if ck.is_file():
        try:
            c = load_checkpoint(ck)
            return f"step {c.step}/{int(c.config.get('iterations', 0))}"
        except (ValueError, OSError) as e:
            return f"an unreadable checkpoint: {e}"
    if (folder / "metrics.json").is_file():
        return "finished, no checkpoint"
    return None


def held_run_message(
    folder: str | Path, held: str, resume: str = "--resume", overwrite: str = "--overwrite"
) -> str:
    """The message refusing a new run in ``folder``, which holds a run (``held``: :func:`describe_run`).

    A run with a checkpoint can be continued (``resume``); a finished run whose checkpoint is gone
    cannot, so only ``overwrite`` (or another folder) is offered.

    Example:
        >>> print(held_run_message("runs/a", "step 200/3000"))
        runs/a holds a run (step 200/3000); use --resume to continue or --overwrite to start over
    """
    if held.startswith("finished"):
        return (
            f"{folder} holds a finished run whose checkpoint is gone (nothing to resume); "
            f"use {overwrite} to start over or another folder"
        )
    return f"{folder} holds a run ({held}); use {resume} to continue or {overwrite} to start over"


#: The files a run writes at the top of its folder (a file of these names that vadgs did not write
#: is refused rather than written over: :func:`check_new_run`).
RUN_FILES = (CHECKPOINT_NAME, "config.json", "log.jsonl", "metrics.json")


def check_new_run(
    folder: str | Path,
    overwrite: bool,
    flag: str = "--out",
    resume: str = "--resume",
    overwrite_flag: str = "--overwrite",
) -> tuple[str | None, list[Path]]:
    """Check ``folder`` for a new run, before any work; ``(the run it holds or None, files to remove)``.

    A new path or an empty folder is fine; a folder vadgs did not write is refused with or without
    ``overwrite`` (:func:`vadgs.runfolder.check_output_folder`), as is a vadgs folder holding,
    under a name the run writes (:data:`RUN_FILES`), a file vadgs did not write; a folder holding
    a run needs ``overwrite``, and then every file to remove is checked
    (:func:`vadgs.runfolder.check_removable`: a manifest entry outside the folder, a symbolic
    link on the way, a read-only folder stop it here, before anything is removed).

    Raises:
        ValueError: one line, naming the folder and (for a run) ``resume`` / ``overwrite_flag``.
        vadgs.runfolder.ManifestError: an unreadable manifest, or an entry outside the folder.
        PermissionError: a folder of a file to remove is not writable.
    """
    from vadgs.runfolder import check_output_folder, check_removable, check_unrecorded

    folder = Path(folder)
    check_output_folder(folder, flag, "vadgs run")
    held = describe_run(folder) if folder.is_dir() else None
    if held is not None and not overwrite:
        raise ValueError(held_run_message(folder, held, resume, overwrite_flag))
    files = check_removable(folder) if overwrite and folder.is_dir() else []
    doomed = {p.absolute() for p in files}
    check_unrecorded(folder, [n for n in RUN_FILES if (folder / n).absolute() not in doomed], flag)
    return held, files


def clear_run(folder: str | Path) -> list[Path]:
    """Remove what vadgs wrote into a run folder, and nothing else (:func:`vadgs.runfolder.remove_recorded`).

    The files recorded in the run's manifest, then the folders that became empty. Everything
    is checked first (a symbolic link on the way, e.g. a linked ``ply/``, or a folder that is not
    writable raises, naming it, before anything is removed). The lock file, files the user put
    there (a video in ``renders/``) and a COLMAP run's ``undistorted/`` (which a new run replaces)
    stay.

    Returns:
        The removed files (and the temporary files of a killed run).
    """
    from vadgs.runfolder import remove_recorded

    folder = Path(folder)
    removed = remove_recorded(folder)
    removed += remove_run_tmp(folder)
    return removed
