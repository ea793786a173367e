"""The project folder that ``vadgs sfm`` writes: what of an existing one it may replace, and how.

A project is ``vadgs sfm``'s when its ``sfm.json`` says so (:func:`vadgs.runfolder.is_sfm_project`).
:func:`check_sfm_project` refuses any other non-empty folder (a COLMAP project made elsewhere is
never written to) and, in one of its own, lists what a new run replaces (:class:`ReplacedFiles`:
``sparse/0``, ``database.db`` and the photos it put into ``images/``, listed in ``sfm.json``'s
``images_written``), never the project's other files. :func:`check_out_outside` keeps the project
out of the photo folder; :func:`place_photos` puts the photos into ``images/`` (copies, symbolic
links, or upright copies of the rotated ones); :func:`move_into` and :func:`remove_path` move the
finished work into place. :func:`vadgs.data.sfm.run_sfm` uses them all.
"""

from __future__ import annotations

import json
import os
import shutil
from collections.abc import Sequence
from pathlib import Path
from typing import NamedTuple

from vadgs.data.images import upright_image
from vadgs.runfolder import is_sfm_project

__all__ = [
    "PROJECT_ENTRIES",
    "ReplacedFiles",
    "check_out_outside",
    "check_sfm_project",
    "move_into",
    "place_photos",
    "remove_path",
]

#: What :func:`vadgs.data.sfm.run_sfm` writes into the project (and ``overwrite`` replaces).
PROJECT_ENTRIES = ("images", "sparse", "database.db", "sfm.json")


def _read_summary(project: Path) -> dict | None:
    try:
        data = json.loads((project / "sfm.json").read_text(encoding="utf-8"))
    except (OSError, ValueError, RecursionError):
        return None
    return data if isinstance(data, dict) else None


def _written_images(project: Path) -> list[str]:
    """The files of ``project/images`` that ``vadgs sfm`` wrote there (names relative to it).

    The list in its ``sfm.json`` (``images_written``).

    Raises:
        ValueError: an ``sfm.json`` without that list (nothing can tell which files are its).
    """
    data = _read_summary(project) or {}
    written = data.get("images_written")
    if not (isinstance(written, list) and all(isinstance(n, str) for n in written)):
        raise ValueError(
            f"--out {project}: cannot tell which files of {project / 'images'} vadgs sfm wrote (its "
            "sfm.json lists no images_written); nothing was changed: give a new or empty folder"
        )
    images = project / "images"
    return sorted({n for n in written if _inside(images, n)})


def _inside(folder: Path, name: str) -> bool:
    """``folder / name`` is a path below ``folder`` (no absolute path, ``..`` or symlinked folder)."""
    from pathlib import PurePosixPath

    pure = PurePosixPath(name)
    if not name or pure.is_absolute() or ".." in pure.parts:
        return False
    cur = folder
    for part in pure.parts[:-1]:
        cur = cur / part
        if cur.is_symlink():
            return False
    return True


class ReplacedFiles(NamedTuple):
    """What a run replaces in an existing project of its own (all empty for a new project).

    Attributes:
        entries: ``database.db``, ``sparse/0``.
        images: the photos it wrote into ``images/`` before.
    """

    entries: list[Path]
    images: list[Path]


def check_sfm_project(
    project: Path, photos: Path, overwrite: bool, names: Sequence[str] = ()
) -> ReplacedFiles:
    """What of ``project`` a run replaces; refuses a project that vadgs sfm did not write.

    A project is ``vadgs sfm``'s when its ``sfm.json`` says so
    (:func:`vadgs.runfolder.is_sfm_project`); any other COLMAP project (or a folder of other
    files) is never written to, with or without ``overwrite``. In one of its own, only what it
    wrote is replaced: ``sparse/0``, ``database.db``, ``sfm.json`` and the photos it put into
    ``images/`` (:func:`_written_images`), never the project's other files, and never a file of
    ``images/`` that a new photo would land on but that it did not write.
    """
    if project.exists() and not project.is_dir():
        raise ValueError(f"--out {project}: expected a folder, got an existing file")
    in_place = (project / "images").resolve() == photos.resolve()
    held = [
        e
        for e in PROJECT_ENTRIES
        if (project / e).exists() or (project / e).is_symlink()
        if not (e == "images" and in_place)
    ]
    from vadgs.runfolder import foreign_entries

    others = [e for e in foreign_entries(project) if not (e == "images" and in_place)]
    ours = project.is_dir() and is_sfm_project(project)
    if others and not ours:  # a COLMAP project made elsewhere, or other files: not ours to write
        shown = ", ".join(others[:5]) + (f", ... ({len(others)} entries)" if len(others) > 5 else "")
        if {"sparse", "database.db", "sfm.json"} & set(held):
            why = "its sfm.json is not vadgs sfm's" if "sfm.json" in held else "no sfm.json of vadgs sfm"
            raise ValueError(
                f"--out {project}: holds a COLMAP project that vadgs sfm did not write ({shown}; {why}); "
                "vadgs sfm never writes into it, its images/ least of all: nothing was changed: give a "
                "new or empty folder"
            )
        raise ValueError(
            f"--out {project}: destination path '{project}' already exists and is not an empty "
            f"directory (holds {shown}) nor a vadgs sfm project; nothing was changed: give a new or "
            "empty folder"
        )
    if not ours:
        return ReplacedFiles([], [])
    if not overwrite:
        raise ValueError(f"--out {project}: already holds {', '.join(held)}; --overwrite replaces them")
    for link in ("sparse", "sparse/0", "images"):
        if (project / link).is_symlink() and not (link == "images" and in_place):
            raise ValueError(
                f"--out {project}: {project / link} is a symbolic link (to {os.readlink(project / link)}); "
                "vadgs sfm does not replace through links; nothing was changed"
            )
    entries = [p for p in (project / "database.db", project / "sparse" / "0") if p.exists() or p.is_symlink()]
    images = [] if in_place else [project / "images" / n for n in _written_images(project)]
    images = [p for p in images if p.is_file() or p.is_symlink()]
    for entry in (*entries, *images):
        if photos.resolve().is_relative_to(entry.resolve()):
            raise ValueError(f"PHOTOS {photos}: is inside {entry}, which --overwrite would replace")
    if not in_place:
        mine = {p.absolute() for p in images}
        clash = [
            n
            for n in names
            if (project / "images" / n).exists() and (project / "images" / n).absolute() not in mine
        ]
        if clash:
            raise ValueError(
                f"--out {project}: {project / 'images'} holds {', '.join(clash[:3])} that vadgs sfm did not "
                "write, where it would put a photo of that name; nothing was changed: move it away or give "
                "a new folder"
            )
    return ReplacedFiles(entries, images)


def remove_path(path: Path) -> None:
    """Remove a file, a symbolic link or a folder tree (nothing when it does not exist)."""
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path)
    else:
        path.unlink(missing_ok=True)


def move_into(src: Path, dst: Path) -> None:
    """Move the tree ``src`` into ``dst`` file by file (``dst``'s other files stay)."""
    for path in sorted(src.rglob("*")):
        if path.is_dir() and not path.is_symlink():
            continue
        target = dst / path.relative_to(src)
        target.parent.mkdir(parents=True, exist_ok=True)
        os.replace(path, target)


def check_out_outside(photos: Path, out: Path) -> None:
    """``--out`` is neither ``PHOTOS`` nor inside it (a project's copies are no photos of a next run)."""
    if out.exists() and not out.is_dir():
        raise ValueError(f"--out {out}: expected a folder, got an existing file")
    if out.resolve() == photos.resolve():
        raise ValueError(
            f"--out {out}: is PHOTOS itself; give the project its own folder (e.g. {out}_project)"
        )
    if out.resolve().is_relative_to(photos.resolve()):
        raise ValueError(
            f"--out {out}: is inside PHOTOS {photos}, where its copies of the photos would be taken as "
            "photos by the next run; give a folder outside PHOTOS"
        )


def place_photos(photos: Path, names: Sequence[str], images: Path, link: bool) -> None:
    """The photos under ``images`` with their names: copies (bytes and times) or absolute symlinks.

    A photo with an EXIF rotation is written upright (:func:`upright_image`), a file even with ``link``.
    """
    for name in names:
        dst = images / name
        dst.parent.mkdir(parents=True, exist_ok=True)
        if upright_image(photos / name, dst) != 1:
            continue
        if link:
            dst.symlink_to((photos / name).resolve())
        else:
            shutil.copy2(photos / name, dst)
