"""What vadgs wrote into a folder: the manifest of a run (or output) folder, and its safe removal.

Every file vadgs writes into a run folder (``checkpoint.pt``, ``log.jsonl``, ``config.json``,
``metrics.json``, ``ply/*``, ``eval*.json``, the panels in ``renders/``, ``export/...``) is
recorded, as it is written, in the folder's manifest :data:`MANIFEST` (``.vadgs/manifest.json``:
paths relative to the folder, rewritten with :func:`~vadgs.io.atomic_write`). Output folders that
``vadgs export --out`` / ``vadgs render --out`` write outside a run, and a ``vadgs batch`` folder,
get one too. The manifest is what lets ``--overwrite`` remove exactly what vadgs wrote:

- :func:`record_files` adds written files; :func:`recorded_files` lists them (for a run written
  by an older vadgs, without a manifest, the exact file names that vadgs wrote: :data:`LEGACY_PATTERNS`);
- :func:`check_removable` checks, before anything is deleted, that every recorded file can be
  removed (no symbolic link on the way, e.g. a linked ``ply/``; writable folders), naming the
  path that cannot; :func:`remove_recorded` then removes them and the folders that became empty;
- :func:`check_output_folder` refuses a non-empty folder that vadgs did not write (no manifest,
  no checkpoint, no ``metrics.json``), as ``git clone`` refuses a non-empty destination.

Files a user put into a run folder (a video in ``renders/``, notes) are never recorded, so they
survive an overwrite.

Example:
    >>> import tempfile
    >>> d = Path(tempfile.mkdtemp())
    >>> _ = (d / "metrics.json").write_text("{}")
    >>> _ = record_files(d, [d / "metrics.json"])
    >>> [p.name for p in recorded_files(d)]
    ['metrics.json']
    >>> [p.name for p in remove_recorded(d)]
    ['metrics.json']
    >>> sorted(p.name for p in d.iterdir())
    []
"""

from __future__ import annotations

import contextlib
import fnmatch
import json
import os
from collections.abc import Iterable
from pathlib import Path

from vadgs.io import atomic_write

__all__ = [
    "LEGACY_PATTERNS",
    "MANIFEST",
    "check_output_folder",
    "check_removable",
    "foreign_entries",
    "has_manifest",
    "is_vadgs_folder",
    "record_files",
    "recorded_files",
    "remove_recorded",
]

MANIFEST = Path(".vadgs") / "manifest.json"
"""The manifest of a folder vadgs writes, relative to the folder."""

_FORMAT = "vadgs-folder-manifest"

LEGACY_PATTERNS = (
    "checkpoint.pt",
    "log.jsonl",
    "config.json",
    "metrics.json",
    "eval.json",
    "eval_novel.json",
    "batch.json",
    "batch_task.json",
    "ply/static.ply",
    "ply/object_*.ply",
    "ply/poses.json",
    "renders/view[0-9][0-9][0-9]_*.png",
    "export/frame[0-9][0-9][0-9]/world_frame[0-9][0-9][0-9].ply",
    "export/frame[0-9][0-9][0-9]/sky.png",
    "export/frame[0-9][0-9][0-9]/sky.json",
    "export/frame[0-9][0-9][0-9]/cameras.json",
    "export/frame[0-9][0-9][0-9]/cfg_args",
    "export/frame[0-9][0-9][0-9]/point_cloud/iteration_*/point_cloud.ply",
    "export/frame[0-9][0-9][0-9]/sparse/0/*.bin",
)
"""The files an older vadgs (before the manifest) wrote into a run folder, as globs: what
:func:`recorded_files` lists for a run without a manifest. Never whole folders."""

_LEGACY_DIRS = ("ply", "renders", "export")  # where the legacy files live (checked for links)
_RUN_MARKERS = ("checkpoint.pt", "metrics.json")
# entries that do not make a folder "not empty": the manifest's folder, the run lock, vadgs's
# write test and temporary files, a COLMAP run's undistorted copy (written before the manifest)
_OWN = (".vadgs", ".vadgs.lock", ".vadgs-write-test-*", ".vadgs-sfm-*", ".*.tmp*", "undistorted")


def _manifest(folder: Path) -> dict[str, dict] | None:
    path = folder / MANIFEST
    if not path.is_file():
        return None
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return {}
    files = data.get("files") if isinstance(data, dict) else None
    return dict(files) if isinstance(files, dict) else {}


def has_manifest(folder: str | Path) -> bool:
    """Whether ``folder`` has a manifest (:data:`MANIFEST`)."""
    return (Path(folder) / MANIFEST).is_file()


def _relative(folder: Path, path: Path) -> str | None:
    """``path`` relative to ``folder`` (lexically, both absolute), or None when outside it."""
    folder, path = Path(os.path.abspath(folder)), Path(os.path.abspath(path))
    try:
        rel = path.relative_to(folder)
    except ValueError:
        return None
    return rel.as_posix() if rel.parts and ".." not in rel.parts else None


def record_files(folder: str | Path, paths: Iterable[str | Path]) -> Path | None:
    """Record in ``folder``'s manifest that vadgs wrote ``paths`` (those outside ``folder`` are skipped).

    The manifest is rewritten atomically, and only when something new is recorded (a file's size
    is kept as written). Call it right after each write, while the folder's lock is held.

    Returns:
        The manifest's path, or None when nothing was inside ``folder``.
    """
    folder = Path(folder)
    files = _manifest(folder) or {}
    changed, inside = False, False
    for p in paths:
        rel = _relative(folder, Path(p))
        if rel is None:
            continue
        inside = True
        try:
            size = (folder / rel).stat().st_size
        except OSError:
            size = None
        if files.get(rel, {}).get("size", -1) != size or rel not in files:
            files[rel] = {"size": size}
            changed = True
    if not inside:
        return None
    path = folder / MANIFEST
    if changed or not path.is_file():
        atomic_write(path, json.dumps({"format": _FORMAT, "version": 1, "files": files}, indent=1) + "\n")
    return path


def _legacy(folder: Path) -> list[Path]:
    found: list[Path] = []
    for pattern in LEGACY_PATTERNS:
        found += sorted(p for p in folder.glob(pattern) if p.is_file() or p.is_symlink())
    return found


def recorded_files(folder: str | Path) -> list[Path]:
    """The files vadgs wrote into ``folder`` that are still there (absolute or as given).

    With a manifest: its entries; without one (a run of an older vadgs): the existing files whose
    names match :data:`LEGACY_PATTERNS`, when the folder holds a run (``checkpoint.pt`` or
    ``metrics.json``), else none.
    """
    folder = Path(folder)
    files = _manifest(folder)
    if files is None:
        return _legacy(folder) if any((folder / m).is_file() for m in _RUN_MARKERS) else []
    return [folder / rel for rel in sorted(files) if (folder / rel).is_file() or (folder / rel).is_symlink()]


def is_vadgs_folder(folder: str | Path) -> bool:
    """Whether vadgs wrote ``folder``: it has a manifest, a ``checkpoint.pt`` or a ``metrics.json``."""
    folder = Path(folder)
    return has_manifest(folder) or any((folder / m).is_file() for m in _RUN_MARKERS)


def foreign_entries(folder: str | Path) -> list[str]:
    """The names in ``folder`` that are not vadgs's own bookkeeping (sorted; ``[]``: empty)."""
    folder = Path(folder)
    if not folder.is_dir():
        return []
    return sorted(e.name for e in folder.iterdir() if not any(fnmatch.fnmatch(e.name, g) for g in _OWN))


def check_output_folder(folder: str | Path, flag: str = "--out", what: str = "vadgs") -> Path:
    """Refuse ``folder`` when it is a non-empty folder that vadgs did not write.

    A new path, an empty folder, or a folder vadgs wrote (:func:`is_vadgs_folder`) passes.

    Args:
        folder: the output folder.
        flag: how the message names it.
        what: whose folder it should be, for the message (e.g. ``"vadgs run"``).

    Raises:
        ValueError: ``"--out x: destination path 'x' already exists and is not an empty directory
            (holds a, b, c, ...) nor a vadgs run; ..."``, in one line.
    """
    folder = Path(folder)
    if not folder.is_dir() or is_vadgs_folder(folder):
        return folder
    entries = foreign_entries(folder)
    if not entries:
        return folder
    shown = ", ".join(entries[:5]) + (f", ... ({len(entries)} entries)" if len(entries) > 5 else "")
    raised = f" (-> {folder.resolve()})" if folder.is_symlink() else ""
    raise ValueError(
        f"{flag} {folder}: destination path '{folder}'{raised} already exists and is not an empty "
        f"directory (holds {shown}) nor a {what} folder; nothing was changed: give a new or empty folder"
    )


def _links_on_the_way(folder: Path, path: Path) -> Path | None:
    """The first symbolic link among ``path`` and its parents below ``folder``, or None."""
    rel = path.relative_to(folder)
    cur = folder
    for part in rel.parts:
        cur = cur / part
        if cur.is_symlink():
            return cur
    return None


def check_removable(folder: str | Path) -> list[Path]:
    """Check that every recorded file of ``folder`` can be removed; the files, nothing removed yet.

    Raises:
        ValueError: a symbolic link on the way to a recorded file or in place of one of vadgs's
            folders (``ply``, ``renders``, ``export``, ``.vadgs``), named: vadgs does not remove
            what a link points to.
        PermissionError: a folder holding a recorded file is not writable, named.
    """
    folder = Path(folder)
    for name in (*_LEGACY_DIRS, ".vadgs"):
        if (folder / name).is_symlink():
            target = os.readlink(folder / name)
            raise ValueError(
                f"{folder / name} is a symbolic link (to {target}); vadgs writes a real folder there "
                f"and does not remove through links: remove or replace the link first; nothing was removed"
            )
    files = recorded_files(folder)
    for p in files:
        link = _links_on_the_way(folder, p)
        if link is not None and link != p:
            raise ValueError(
                f"{link} is a symbolic link (to {os.readlink(link)}); vadgs does not remove through "
                f"links: remove or replace the link first; nothing was removed"
            )
        if not os.access(p.parent, os.W_OK | os.X_OK):
            raise PermissionError(f"{p.parent}: not writable, cannot remove {p.name}; nothing was removed")
    return files


def remove_recorded(folder: str | Path) -> list[Path]:
    """Remove what vadgs wrote into ``folder`` (:func:`recorded_files`), after checking it all.

    First :func:`check_removable` (so a refused removal leaves everything as it was), then the
    files, the manifest, and the folders that became empty on the way (a folder still holding a
    user's file stays). The folder itself stays.

    Returns:
        The removed files.
    """
    folder = Path(folder)
    files = check_removable(folder)
    removed = []
    for p in files:
        p.unlink(missing_ok=True)
        removed.append(p)
    (folder / MANIFEST).unlink(missing_ok=True)
    written = [*files, folder / MANIFEST]
    parents = {q for p in written for q in p.parents if q != folder and folder in q.parents}
    for d in sorted(parents, key=lambda q: len(q.parts), reverse=True):
        with contextlib.suppress(OSError):
            d.rmdir()  # only when empty
    return removed
