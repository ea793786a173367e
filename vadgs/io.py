"""Atomic file writes: every file vadgs writes into a run folder goes through :func:`atomic_write`.

A write goes to a temporary file beside the target (``.NAME.XXXXXXXX.tmpSUFFIX``, same folder, so
the rename is atomic on one filesystem), is flushed and fsynced, and then replaces the target with
:func:`os.replace`. An interrupted or failed write leaves the previous file untouched and removes its
temporary file; a killed process may leave one behind, which :func:`remove_stale_tmp` clears.

Example:
    >>> import tempfile, pathlib
    >>> d = pathlib.Path(tempfile.mkdtemp())
    >>> _ = write_json(d / "metrics.json", {"psnr": 29.3})
    >>> json.loads((d / "metrics.json").read_text())
    {'psnr': 29.3}
"""

from __future__ import annotations

import json
import os
import re
import secrets
from collections.abc import Callable
from pathlib import Path
from typing import Any

__all__ = ["TMP_GLOB", "atomic_write", "check_inside", "remove_stale_tmp", "safe_filename", "write_json"]

TMP_GLOB = ".*.tmp*"
"""Glob of the temporary files :func:`atomic_write` creates (in the target's folder)."""


def _tmp_path(path: Path) -> Path:
    # the target's suffix is kept last, so writers that pick a format by suffix (PIL, imageio) work
    return path.with_name(f".{path.stem}.{secrets.token_hex(4)}.tmp{path.suffix}")


def atomic_write(path: str | Path, data: str | bytes | Callable[[Path], Any]) -> Path:
    """Write ``data`` to ``path`` atomically: all of it, or nothing and the previous file kept.

    Args:
        path: the file to write; its folder is created.
        data: text (written as UTF-8), bytes, or a function that writes a file at the path it is
            given (the temporary file, whose suffix is ``path``'s), e.g. ``lambda p: torch.save(obj, p)``.

    Returns:
        ``path`` as a :class:`~pathlib.Path`.

    Raises:
        TypeError: ``data`` is none of the three.
        OSError: from the write or the rename; the temporary file is removed first.
    """
    if not isinstance(data, (str, bytes, bytearray)) and not callable(data):
        raise TypeError(
            f"atomic_write: data must be str, bytes or a function of a path, got {type(data).__name__}"
        )
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = _tmp_path(path)
    try:
        if callable(data):
            data(tmp)
        elif isinstance(data, str):
            tmp.write_text(data, encoding="utf-8")
        else:
            tmp.write_bytes(bytes(data))
        fd = os.open(tmp, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return path


def write_json(path: str | Path, obj: Any, indent: int | None = 2, **kwargs: Any) -> Path:
    """``json.dumps(obj, indent=indent, **kwargs)`` plus a newline, written with :func:`atomic_write`."""
    return atomic_write(path, json.dumps(obj, indent=indent, **kwargs) + "\n")


def remove_stale_tmp(folder: str | Path, *subfolders: str) -> list[Path]:
    """Remove the temporary files a killed writer left in ``folder`` (and in its ``subfolders``).

    Returns:
        the removed paths.
    """
    removed = []
    for sub in ("", *subfolders):
        for p in (Path(folder) / sub).glob(TMP_GLOB):
            if p.is_file():
                p.unlink(missing_ok=True)
                removed.append(p)
    return removed


_UNSAFE = re.compile(r"[^A-Za-z0-9._+-]+")


def safe_filename(name: object) -> str:
    r"""``name`` (a camera, image or instance name from a dataset) as one safe file-name component.

    Every run of characters other than letters, digits, ``. _ + -`` becomes ``_`` (so no ``/``,
    ``\``, NUL or space survives), and leading dots are replaced, so the result can neither leave
    its folder (``..``) nor hide (``.name``). Names of dataset files are made safe with it before
    a path is built from them; the scene's own metadata keeps the original name.

    Example:
        >>> safe_filename("front_left"), safe_filename("../../etc/passwd"), safe_filename("")
        ('front_left', '__.._etc_passwd', '_')
    """
    text = _UNSAFE.sub("_", str(name))
    text = re.sub(r"^\.+", "_", text)
    return text[:200] or "_"


def check_inside(path: str | Path, root: str | Path, what: str) -> Path:
    """``path`` if it lies inside the folder ``root`` once both are resolved (symlinks followed).

    Raises:
        ValueError: ``"<what>: <path> resolves to <real>, outside <root>"``.

    Example:
        >>> check_inside("/tmp/run/renders/a.png", "/tmp/run", "panel")
        PosixPath('/tmp/run/renders/a.png')
    """
    path, root = Path(path), Path(root)
    real, real_root = path.resolve(), root.resolve()
    if real != real_root and real_root not in real.parents:
        raise ValueError(f"{what}: {path} resolves to {real}, outside {root}")
    return path
