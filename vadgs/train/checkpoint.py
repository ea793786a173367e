"""Checkpoints of a run: the file, its checksum, atomic saving, loading, and what a resume may change.

A checkpoint is one ``torch.save`` file (``checkpoint.pt`` in the run folder) of plain tensors and
containers (read with ``weights_only``), with a format name, a version and a SHA-256 checksum of
its content; :class:`~vadgs.train.trainer.Trainer` writes and reads it
(:meth:`~vadgs.train.trainer.Trainer.checkpoint_payload`,
:meth:`~vadgs.train.trainer.Trainer.from_checkpoint`). :func:`describe_run` says what run a folder
holds; :func:`clear_run` removes one.
"""

from __future__ import annotations

import errno
import hashlib
import os
import shutil
import warnings
from pathlib import Path
from typing import Any

import torch

from vadgs.io import atomic_write, remove_stale_tmp

__all__ = [
    "CHECKPOINT_NAME",
    "RESUMABLE_CHANGES",
    "checkpoint_checksum",
    "clear_run",
    "describe_run",
    "load_checkpoint",
]

CHECKPOINT_NAME = "checkpoint.pt"
_FORMAT = "vadgs-train-checkpoint"
_VERSION = 1


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
            free = shutil.disk_usage(path.parent).free
            code = errno.ENOSPC if free < (1 << 20) else errno.EIO
            why = os.strerror(code) if code == errno.ENOSPC else " ".join(str(e).split())[:200]
        raise OSError(code, f"cannot write ({why}); {kept}", str(path)) from e


def _remove_stale_tmp(folder: Path) -> list[Path]:
    """Remove temporary files a killed run left behind (of checkpoints, JSON files and exports)."""
    removed = remove_stale_tmp(folder, "ply")
    # the names written before vadgs.io
    for pattern in (CHECKPOINT_NAME + ".tmp", "ply/.*.partial.*"):
        for p in folder.glob(pattern):
            if p.is_file():
                p.unlink(missing_ok=True)
                removed.append(p)
    return removed


def load_checkpoint(path: str | Path) -> dict[str, Any]:
    """Read a checkpoint written by :class:`Trainer` (``weights_only`` unpickling).

    Raises:
        FileNotFoundError: if it does not exist.
        ValueError: if it is corrupt, truncated, modified (its SHA-256 checksum does not match) or
            not a vadgs training checkpoint. A checkpoint without a checksum (older vadgs) loads
            with a warning.
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
    if not isinstance(ckpt, dict) or ckpt.get("format") != _FORMAT:
        raise ValueError(f"checkpoint {path}: not a vadgs training checkpoint")
    if int(ckpt.get("version", -1)) != _VERSION:
        raise ValueError(f"checkpoint {path}: unsupported version {ckpt.get('version')}")
    missing = [
        k
        for k in ("step", "config", "model", "model_extra", "optimizer", "strategy_state", "sampler", "rng")
        if k not in ckpt
    ]
    if missing:
        raise ValueError(f"checkpoint {path}: missing entries {missing}")
    if "checksum" not in ckpt:
        warnings.warn(
            f"checkpoint {path}: no checksum (written by an older vadgs); its content is not verified",
            stacklevel=2,
        )
    elif checkpoint_checksum(ckpt) != ckpt["checksum"]:
        raise ValueError(f"checkpoint {path}: checksum mismatch: the file was modified or is corrupt")
    return ckpt


RESUMABLE_CHANGES = (
    "iterations",
    "max_minutes",
    "device",
    "threads",
    "checkpoint_every",
    "checkpoint_minutes",
    "log_every",
)
"""The :class:`TrainConfig` fields :meth:`Trainer.from_checkpoint` can change (the others define the run)."""


# ---------------------------------------------------------------------------------------------------
# the run folder

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
