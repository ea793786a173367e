"""Argument types and helpers shared by the ``vadgs`` commands."""

from __future__ import annotations

import argparse
import math
import os
import tempfile
from collections.abc import Callable
from pathlib import Path


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
