"""What vadgs wrote into a folder: the manifest of a run (or output) folder, and its safe removal.

Every file vadgs writes into a run folder (``checkpoint.pt``, ``log.jsonl``, ``config.json``,
``metrics.json``, ``ply/*``, ``eval*.json``, the panels in ``renders/``, ``export/...``) is
recorded, as it is written, in the folder's manifest :data:`MANIFEST` (``.vadgs/manifest.json``:
paths relative to the folder, rewritten with :func:`~vadgs.io.atomic_write`; format version
:data:`FOLDER_VERSION`: a folder of another version is refused in one line, its run to be trained
again). Output folders that ``vadgs export --out`` / ``vadgs render --out`` write outside a run,
and a ``vadgs batch`` folder, get one too. The manifest is what lets ``--overwrite`` remove exactly
what vadgs wrote:

- :func:`record_files` adds written files; :func:`recorded_files` lists them;
- :func:`check_removable` checks, before anything is deleted, that every entry of the manifest is
  a relative path inside the folder once resolved (no absolute path, no ``..``, no symbolic link
  on the way, e.g. a linked ``ply/``) and that its folder is writable, naming the entry and the
  manifest that do not (:class:`ManifestError`); :func:`remove_recorded` then removes them and
  the folders, named by those entries, that became empty;
- :func:`is_vadgs_folder` says whether vadgs wrote a folder: its manifest, never file names;
  :func:`check_output_folder` refuses any other non-empty folder, as ``git clone`` refuses a
  non-empty destination, and a folder whose manifest cannot be read;
- a manifest's ``kind`` (``"segment"``: a scene :func:`vadgs.data.synthetic.make_segment`
  wrote) keeps such a folder from the other writers (:func:`manifest_kind`);
  :func:`is_sfm_project` says whether ``vadgs sfm`` wrote a COLMAP project (its ``sfm.json``).

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
from pathlib import Path, PurePosixPath, PureWindowsPath

from vadgs.io import atomic_write

__all__ = [
    "FOLDER_VERSION",
    "MANIFEST",
    "SFM_FORMAT",
    "ManifestError",
    "check_entries",
    "check_output_folder",
    "check_removable",
    "check_unrecorded",
    "describe_files",
    "entry_problem",
    "foreign_entries",
    "has_manifest",
    "is_sfm_project",
    "is_vadgs_folder",
    "manifest_kind",
    "read_manifest",
    "record_files",
    "recorded_files",
    "remove_files",
    "remove_recorded",
]

MANIFEST = Path(".vadgs") / "manifest.json"
"""The manifest of a folder vadgs writes, relative to the folder."""

_FORMAT = "vadgs-folder-manifest"

FOLDER_VERSION = 2
"""The format version of the folders (manifests) this vadgs writes and reads (2: issue 50, nothing
older read)."""


SFM_FORMAT = "vadgs-sfm-project"
"""The ``format`` of the ``sfm.json`` that ``vadgs sfm`` (:func:`vadgs.data.sfm.run_sfm`) writes:
what makes a COLMAP project vadgs's."""


def is_sfm_project(project: str | Path) -> bool:
    """Whether ``vadgs sfm`` wrote the COLMAP project ``project``: its ``sfm.json`` says so.

    The ``format`` :data:`SFM_FORMAT`. A COLMAP project made elsewhere (COLMAP's GUI, nerfstudio,
    another tool's ``sfm.json``) is not.
    """
    try:
        data = json.loads((Path(project) / "sfm.json").read_text(encoding="utf-8"))
    except (OSError, ValueError, RecursionError):
        return False
    return isinstance(data, dict) and data.get("format") == SFM_FORMAT


_RUN_DIRS = ("ply", "renders", "export")  # the folders a run writes (never removed through a link)
# entries that do not make a folder "not empty": the manifest's folder, the run lock, vadgs's
# write test and temporary files, a COLMAP run's undistorted copy (written before the manifest)
_OWN = (".vadgs", ".vadgs.lock", ".vadgs-write-test-*", ".vadgs-sfm-*", ".*.tmp*", "undistorted")


class ManifestError(ValueError):
    """A folder's manifest cannot be read, or names a path that is not a file inside the folder.

    Nothing was removed or written when it is raised; the message names the manifest (and the
    entry), says why, and how to go on.
    """


def read_manifest(folder: str | Path) -> dict[str, dict] | None:
    """The entries of ``folder``'s manifest (``{relative path: {"size": ...}}``), or None without one.

    The entries are as written, not checked (:func:`check_removable` checks them).

    Raises:
        ManifestError: the manifest is there but is not vadgs's (unreadable, cut short, not JSON,
            another format), naming it and how to go on.
    """
    folder = Path(folder)
    path = folder / MANIFEST
    if not (path.is_file() or path.is_symlink()):
        return None
    why = None
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError, RecursionError) as e:
        data, why = None, f"{type(e).__name__}: {e}"
    if why is None and not (isinstance(data, dict) and data.get("format") == _FORMAT):
        why = f"not a vadgs manifest (expected format {_FORMAT!r})"
    elif why is None and data.get("version") != FOLDER_VERSION:
        raise ManifestError(
            f"{path}: format version {data.get('version')}, this vadgs reads version {FOLDER_VERSION}: "
            "train the run again (in a new folder)"
        )
    elif why is None and not isinstance(data.get("files"), dict):
        why = "no 'files' object"
    if why is not None:
        raise ManifestError(
            f"{path}: unreadable ({' '.join(why.split())[:200]}): vadgs cannot tell which files in "
            f"{folder} it wrote, so it neither removes nor replaces any; nothing was changed: give "
            f"another folder, or move what you keep out of {folder} and delete it yourself"
        )
    return dict(data["files"])


def has_manifest(folder: str | Path) -> bool:
    """Whether ``folder`` has a manifest file (:data:`MANIFEST`; readable or not)."""
    path = Path(folder) / MANIFEST
    return path.is_file() or path.is_symlink()


def _relative(folder: Path, path: Path) -> str | None:
    """``path`` relative to ``folder`` (lexically, both absolute), or None when outside it."""
    folder, path = Path(os.path.abspath(folder)), Path(os.path.abspath(path))
    try:
        rel = path.relative_to(folder)
    except ValueError:
        return None
    return rel.as_posix() if rel.parts and ".." not in rel.parts else None


def manifest_kind(folder: str | Path) -> str | None:
    """The ``kind`` a folder's manifest declares, or None (a run or an output folder; no manifest).

    ``"segment"``: a scene that :func:`vadgs.data.synthetic.make_segment` wrote.

    Raises:
        ManifestError: an unreadable manifest (:func:`read_manifest`).
    """
    folder = Path(folder)
    if read_manifest(folder) is None:
        return None
    kind = json.loads((folder / MANIFEST).read_text(encoding="utf-8")).get("kind")
    return kind if isinstance(kind, str) else None


def record_files(folder: str | Path, paths: Iterable[str | Path], kind: str | None = None) -> Path | None:
    """Record in ``folder``'s manifest that vadgs wrote ``paths`` (those outside ``folder`` are skipped).

    The manifest is rewritten atomically, and only when something new is recorded (a file's size
    is kept as written). Call it right after each write, while the folder's lock is held.

    Args:
        folder: the folder.
        paths: the files written.
        kind: what the folder is, when it is no run nor output folder (``"segment"``): kept in the
            manifest; :func:`check_output_folder` refuses such a folder to other writers.

    Returns:
        The manifest's path, or None when nothing was inside ``folder``.

    Raises:
        ManifestError: the folder's manifest is unreadable (:func:`read_manifest`): it is not
            replaced by one that forgets what it held.
    """
    folder = Path(folder)
    files = read_manifest(folder) or {}
    kind = kind or manifest_kind(folder)
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
        entry = files.get(rel)
        if not isinstance(entry, dict) or entry.get("size", -1) != size:
            files[rel] = {"size": size}
            changed = True
    if not inside:
        return None
    path = folder / MANIFEST
    if changed or not path.is_file():
        data: dict = {
            "format": _FORMAT,
            "version": FOLDER_VERSION,
            **({"kind": kind} if kind else {}),
            "files": files,
        }
        atomic_write(path, json.dumps(data, indent=1) + "\n")
    return path


def recorded_files(folder: str | Path) -> list[Path]:
    """The files vadgs wrote into ``folder`` that are still there, checked (:func:`check_entries`).

    The manifest's entries; none without a manifest.

    Raises:
        ManifestError: an unreadable manifest, or an entry that is not a file inside ``folder``.
    """
    folder = Path(folder)
    files = read_manifest(folder)
    if files is None:
        return []
    checked = check_entries(folder, files)
    return [p for p in checked if p.is_file() or p.is_symlink()]


def is_vadgs_folder(folder: str | Path) -> bool:
    """Whether vadgs wrote ``folder``: it has a manifest (not file names).

    A folder whose manifest is unreadable counts as vadgs's here; :func:`check_output_folder`
    refuses it.
    """
    return has_manifest(folder)


def foreign_entries(folder: str | Path) -> list[str]:
    """The names in ``folder`` that are not vadgs's own bookkeeping (sorted; ``[]``: empty)."""
    folder = Path(folder)
    if not folder.is_dir():
        return []
    return sorted(e.name for e in folder.iterdir() if not any(fnmatch.fnmatch(e.name, g) for g in _OWN))


def check_output_folder(folder: str | Path, flag: str = "--out", what: str = "vadgs") -> Path:
    """Refuse ``folder`` when it is a non-empty folder that vadgs did not write.

    A new path, an empty folder, or a folder vadgs wrote (:func:`is_vadgs_folder`: a readable
    manifest of this format version) passes. The message never offers ``--overwrite`` or
    ``--resume``: they are for vadgs's own folders.

    Args:
        folder: the output folder.
        flag: how the message names it.
        what: whose folder it should be, for the message (e.g. ``"vadgs run"``).

    Raises:
        ValueError: ``"--out x: destination path 'x' already exists and is not an empty directory
            (holds a, b, c, ...) nor a vadgs run; ..."``, in one line.
        ManifestError: the folder's manifest is unreadable or of another format version
            (:func:`read_manifest`).
    """
    folder = Path(folder)
    if not folder.is_dir():
        return folder
    kind = manifest_kind(folder)
    if kind is not None:  # vadgs wrote it, as something else (a scene make_segment wrote)
        raise ValueError(
            f"{flag} {folder}: holds a {kind} that vadgs wrote (its manifest says so), not a {what} "
            "folder; nothing was changed: give a new or empty folder"
        )
    if has_manifest(folder):
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
    """The first symbolic link among ``path``'s parents below ``folder`` (``path`` itself not), or None."""
    cur = folder
    for part in path.relative_to(folder).parts[:-1]:
        cur = cur / part
        if cur.is_symlink():
            return cur
    return None


def entry_problem(folder: str | Path, rel: str) -> str | None:
    """Why ``rel`` (a manifest entry) is not a file path inside ``folder``, or None when it is.

    Checked as a resolved path: a relative path, no ``..``, no symbolic link among its folders
    (the file itself may be a link), inside ``folder`` once resolved.

    Example:
        >>> entry_problem("/tmp", "../victim.txt"), entry_problem("/tmp", "/etc/passwd")
        ("goes up with '..'", 'is an absolute path')
    """
    folder = Path(folder)
    if not isinstance(rel, str) or not rel or "\0" in rel:
        return "is not a file path"
    pure = PurePosixPath(rel)
    if pure.is_absolute() or PureWindowsPath(rel).drive:
        return "is an absolute path"
    if ".." in pure.parts:
        return "goes up with '..'"
    if not pure.parts or pure.parts == (".",):
        return "is the folder itself"
    path = folder / pure
    link = _links_on_the_way(folder, path)
    if link is not None:
        return f"passes through {link}, a symbolic link (to {os.readlink(link)})"
    try:
        real = path.parent.resolve(strict=False)
        base = folder.resolve(strict=False)
    except (OSError, RuntimeError) as e:
        return f"cannot be resolved ({e})"
    if not (real == base or real.is_relative_to(base)):
        return f"resolves to {real / path.name}, outside {base}"
    return None


def check_entries(folder: str | Path, files: Iterable[str]) -> list[Path]:
    """The manifest entries ``files`` of ``folder`` as paths, each checked to be a file inside it.

    Checked as resolved paths: a relative path, no ``..``, no symbolic link among its folders
    (the file itself may be a link: removing it removes the link).

    Raises:
        ManifestError: naming the first entry that is not, the manifest, and that nothing was removed.
    """
    folder = Path(folder)
    out = []
    for rel in sorted(files):
        problem = entry_problem(folder, rel)
        if problem is not None:
            raise ManifestError(
                f"{folder / MANIFEST}: entry {rel!r} {problem}; vadgs removes only the files it wrote "
                f"inside {folder}, and this manifest names another: nothing was removed; remove that "
                "entry from the manifest, or give another folder"
            )
        out.append(folder / PurePosixPath(rel))
    return out


def check_removable(folder: str | Path) -> list[Path]:
    """Check that every recorded file of ``folder`` can be removed; the files, nothing removed yet.

    Raises:
        ManifestError: an unreadable manifest, or an entry that is not a file inside ``folder``
            (an absolute path, ``..``, a symbolic link among its folders), named with the manifest.
        ValueError: a symbolic link in place of one of vadgs's folders (``ply``, ``renders``,
            ``export``, ``.vadgs``), named: vadgs does not remove what a link points to.
        PermissionError: a folder holding a recorded file is not writable, named.
    """
    folder = Path(folder)
    for name in (*_RUN_DIRS, ".vadgs"):
        if (folder / name).is_symlink():
            target = os.readlink(folder / name)
            raise ValueError(
                f"{folder / name} is a symbolic link (to {target}); vadgs writes a real folder there "
                f"and does not remove through links: remove or replace the link first; nothing was removed"
            )
    files = recorded_files(folder)  # checked: no symbolic link on the way (check_entries)
    for p in files:
        if not os.access(p.parent, os.W_OK | os.X_OK):
            raise PermissionError(f"{p.parent}: not writable, cannot remove {p.name}; nothing was removed")
    return files


def check_unrecorded(folder: str | Path, names: Iterable[str], flag: str = "--out") -> None:
    """Refuse a vadgs folder holding, under a name vadgs is about to write, a file vadgs did not write.

    E.g. a ``checkpoint.pt`` of another project put into a run folder whose own checkpoint is
    gone: a new run would write over it.

    Raises:
        ValueError: naming the files, in one line; nothing was changed.
        ManifestError: from :func:`recorded_files`.
    """
    folder = Path(folder)
    if not folder.is_dir():
        return
    mine = {p.absolute() for p in recorded_files(folder)}
    theirs = [n for n in names if (folder / n).exists() and (folder / n).absolute() not in mine]
    if theirs:
        raise ValueError(
            f"{flag} {folder}: holds {', '.join(theirs)} that vadgs did not write (not in its manifest), "
            "where the run would write its own; nothing was changed: move them away or give another folder"
        )


def describe_files(folder: str | Path, files: Iterable[Path], limit: int = 6) -> str:
    """``files`` relative to ``folder``, the first ``limit`` of them, for a message.

    Example:
        >>> describe_files("r", [Path("r/a"), Path("r/ply/b"), Path("r/c")], limit=2)
        'a, ply/b, ... (3 files)'
    """
    names = [Path(p).relative_to(folder).as_posix() for p in files]
    if not names:
        return "no files"
    more = f", ... ({len(names)} files)" if len(names) > limit else ""
    return ", ".join(names[:limit]) + more


def remove_files(folder: str | Path, files: Iterable[Path]) -> list[Path]:
    """Remove ``files`` (checked paths inside ``folder``), then the folders on their way left empty.

    Returns:
        The files removed (those that existed).
    """
    folder = Path(folder)
    files = list(files)
    removed = []
    for p in files:
        if p.is_file() or p.is_symlink():
            p.unlink()
            removed.append(p)
    parents = {q for p in files for q in p.parents if q != folder and folder in q.parents}
    for d in sorted(parents, key=lambda q: len(q.parts), reverse=True):
        if d.is_symlink():
            continue
        with contextlib.suppress(OSError):
            d.rmdir()  # only when empty
    return removed


def remove_recorded(folder: str | Path) -> list[Path]:
    """Remove what vadgs wrote into ``folder`` (:func:`recorded_files`), after checking it all.

    First :func:`check_removable` (so a refused removal leaves everything as it was), then the
    files, the manifest, and the folders that became empty on the way, only those between
    ``folder`` and a checked entry (a folder still holding a user's file stays). The folder
    itself stays.

    Returns:
        The removed files.
    """
    folder = Path(folder)
    files = check_removable(folder)
    removed = remove_files(folder, [*files, folder / MANIFEST])
    return [p for p in removed if p != folder / MANIFEST]
