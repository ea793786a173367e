"""Opening a COLMAP project for ``vadgs train``: undistortion, its cached copy, the reopening recipe.

:func:`open_colmap_project` is what ``vadgs train PATH`` does with a COLMAP folder: find the model
and its images, undistort a model whose cameras are not pinhole (:func:`undistort_colmap`,
pycolmap's undistorter; a ``vadgs sfm`` project keeps its undistorted copy in
``PROJECT/.vadgs-undistorted``, :data:`UNDISTORT_CACHE`), load it
(:func:`vadgs.data.colmap.load_colmap`) and normalise it; the recipe it returns reopens the same
scene (:func:`reopen_colmap_project`). :func:`colmap_logging` quiets pycolmap's log while vadgs
calls it (:data:`COLMAP_LOG_LEVEL`).
"""

from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import os
import shutil
import warnings
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import torch

from vadgs.data.colmap import (
    ColmapScene,
    colmap_normalization,
    colmap_project_name,
    find_images_dir,
    load_colmap,
    transform_colmap,
    warn_exif_rotated,
)
from vadgs.data.colmap_files import check_colmap_images
from vadgs.data.colmap_model import distorted_cameras, find_colmap_model, has_colmap_model, read_colmap_model

__all__ = [
    "COLMAP_LOG_LEVEL",
    "UNDISTORT_CACHE",
    "colmap_logging",
    "open_colmap_project",
    "reopen_colmap_project",
    "undistort_colmap",
]


COLMAP_LOG_LEVEL = 1
"""pycolmap's glog ``minloglevel`` while vadgs calls pycolmap: 0 info, 1 warnings (the default:
undistortion's hundreds of info lines stay quiet), 2 errors. ``vadgs --debug`` sets 0; a level
the caller set higher (``pycolmap.logging.minloglevel``) is kept."""


@contextlib.contextmanager
def colmap_logging(fatal_only: bool = False) -> Iterator[None]:
    """The pycolmap log at :data:`COLMAP_LOG_LEVEL` (or the caller's higher level), restored after.

    Args:
        fatal_only: only fatal errors (``vadgs sfm``'s steps, whose errors are one line each of
            its own), unless :data:`COLMAP_LOG_LEVEL` is 0 (``--debug``: everything).
    """
    import pycolmap

    level = (3 if COLMAP_LOG_LEVEL > 0 else 0) if fatal_only else COLMAP_LOG_LEVEL
    before = pycolmap.logging.minloglevel
    pycolmap.logging.minloglevel = max(before, level)
    try:
        yield
    finally:
        pycolmap.logging.minloglevel = before


def undistort_colmap(
    sparse_dir: str | Path, images_dir: str | Path, out_dir: str | Path
) -> tuple[Path, Path]:
    """Undistort a COLMAP model and its images with :func:`pycolmap.undistort_images`.

    Writes ``out_dir/sparse`` (PINHOLE cameras, the same poses and points) and ``out_dir/images``
    (same names). ``out_dir`` must be new or the output of an earlier call (it is replaced);
    nothing is written next to the input. Every registered image is first decoded in full and
    measured against its camera (:func:`~vadgs.data.colmap_files.check_colmap_images`: pycolmap
    aborts the process on a wrong size and grey-fills a truncated image). The output is written
    to ``.<out_dir name>.partial`` beside ``out_dir`` and renamed when complete, so a failed or
    killed call leaves no half-written ``out_dir``.

    Args:
        sparse_dir: the distorted model.
        images_dir: its images.
        out_dir: where to write.

    Returns:
        ``(sparse, images)`` of the undistorted model, for :func:`load_colmap`.

    Raises:
        FileNotFoundError: if the model, ``images_dir`` or a registered image is missing.
        ValueError: if ``out_dir`` exists and is not an earlier output.
    """
    import pycolmap

    sparse_dir, images_dir, out_dir = Path(sparse_dir), Path(images_dir), Path(out_dir)
    rec = read_colmap_model(sparse_dir, "sparse_dir")
    if not images_dir.is_dir():
        raise FileNotFoundError(f"images_dir: no such folder {images_dir}")
    # pycolmap's undistorter aborts the process on an image of the wrong size and grey-fills a
    # truncated one: every registered image is decoded and measured first, naming the file
    check_colmap_images(rec, images_dir, full=True)
    if out_dir.exists() and not has_colmap_model(out_dir / "sparse"):
        raise ValueError(
            f"out_dir {out_dir}: exists and is not an undistorted COLMAP model; refusing to replace it"
        )
    # written beside out_dir and renamed when complete: a killed run leaves only the partial folder,
    # which the next call removes
    partial = out_dir.with_name(f".{out_dir.name}.partial")
    shutil.rmtree(partial, ignore_errors=True)
    out_dir.parent.mkdir(parents=True, exist_ok=True)
    try:
        with colmap_logging():
            try:
                pycolmap.undistort_images(str(partial), str(sparse_dir), str(images_dir))
            except Exception as e:  # pycolmap's own text, as one line naming the inputs
                first = " ".join(str(e).split())[:200]
                raise ValueError(
                    f"sparse_dir {sparse_dir}, images_dir {images_dir}: pycolmap.undistort_images: {first}"
                ) from None
        if not has_colmap_model(partial / "sparse"):
            raise ValueError(f"out_dir {out_dir}: pycolmap.undistort_images wrote no model")
        if out_dir.exists():
            shutil.rmtree(out_dir)
        partial.rename(out_dir)
    except BaseException:
        shutil.rmtree(partial, ignore_errors=True)  # no half-written copy left in the run folder
        raise
    return out_dir / "sparse", out_dir / "images"


UNDISTORT_CACHE = ".vadgs-undistorted"
"""The folder of a ``vadgs sfm`` project (one with ``sfm.json``) where its undistorted copy is kept."""


def _undistort_key(sparse_dir: Path, images_dir: Path, names: list[str]) -> str:
    """The model's files (bytes) and its registered images (name, size, modification time)."""
    h = hashlib.sha1()
    for f in sorted(sparse_dir.iterdir()):
        if f.is_file():
            h.update(f.name.encode() + b"\0" + f.read_bytes())
    for name in sorted(names):
        st = (images_dir / name).stat()
        h.update(f"{name}\0{st.st_size}\0{st.st_mtime_ns}\n".encode())
    return h.hexdigest()[:20]


def _link_tree(src: Path, dst: Path, partial: Path) -> None:
    """``dst`` a copy of ``src`` of hard links (copies across file systems).

    Written to ``partial`` and renamed when complete.
    """
    shutil.rmtree(partial, ignore_errors=True)
    try:
        for root, _dirs, files in os.walk(src):
            rel = Path(root).relative_to(src)
            (partial / rel).mkdir(parents=True, exist_ok=True)
            for f in files:
                try:
                    os.link(Path(root) / f, partial / rel / f)
                except OSError:
                    shutil.copy2(Path(root) / f, partial / rel / f)
        if dst.exists():
            shutil.rmtree(dst)
        partial.rename(dst)
    except BaseException:
        shutil.rmtree(partial, ignore_errors=True)
        raise


def _undistort_cached(model: Path, images_dir: Path, undistort_dir: Path) -> tuple[Path, Path]:
    """:func:`undistort_colmap`, once per ``vadgs sfm`` project: its copy kept in the project.

    A project that ``vadgs sfm`` wrote (``PROJECT/sparse/0``, ``PROJECT/images``, ``sfm.json``)
    keeps the undistorted model and images in ``PROJECT/.vadgs-undistorted/<key>`` (the key: the
    model's bytes and the images' names, sizes and times; one entry, the last). A run then gets
    hard links to it in ``undistort_dir`` (copies across file systems): no undistortion, no second
    200 MB. Projects made elsewhere are never written to: undistorted into ``undistort_dir`` each time.
    """
    from vadgs.runfolder import is_sfm_project

    project = model.parent.parent
    owned = (
        model.parent.name == "sparse"
        and is_sfm_project(project)  # its sfm.json says so: not a project made elsewhere
        and images_dir.resolve() == (project / "images").resolve()
    )
    if not owned:
        return undistort_colmap(model, images_dir, undistort_dir)
    if undistort_dir.exists() and not has_colmap_model(undistort_dir / "sparse"):
        raise ValueError(
            f"out_dir {undistort_dir}: exists and is not an undistorted COLMAP model; refusing to replace it"
        )
    names = [im.name for im in read_colmap_model(model, "path").images.values() if im.has_pose]
    entry = project / UNDISTORT_CACHE / _undistort_key(model, images_dir, names)
    if has_colmap_model(entry / "sparse") and (entry / "images").is_dir():
        undistort_dir.parent.mkdir(parents=True, exist_ok=True)
        _link_tree(entry, undistort_dir, undistort_dir.with_name(f".{undistort_dir.name}.partial"))
        return undistort_dir / "sparse", undistort_dir / "images"
    out = undistort_colmap(model, images_dir, undistort_dir)
    try:  # the cache is an optimisation: a project that cannot be written to just has none
        for old in entry.parent.glob("*") if entry.parent.is_dir() else ():
            if old.name != entry.name and not old.name.startswith("."):
                shutil.rmtree(old, ignore_errors=True)
        entry.parent.mkdir(exist_ok=True)
        if not entry.exists():  # another run may have stored it meanwhile: never replaced
            _link_tree(undistort_dir, entry, entry.with_name(f".{entry.name}.partial-{os.getpid()}"))
    except OSError as e:
        warnings.warn(
            f"{entry.parent}: cannot keep the undistorted copy ({e}); undistorted again next run",
            stacklevel=3,
        )
    return out


def open_colmap_project(
    path: str | Path,
    images_dir: str | Path | None = None,
    scale: float = 1.0,
    test_every: int = 8,
    normalize: bool = True,
    undistort_dir: str | Path | None = None,
) -> tuple[ColmapScene, dict]:
    """A COLMAP project as a training scene, and the recipe that reopens it identically.

    What ``vadgs train PATH`` does with a COLMAP folder, in order: find the model
    (:func:`find_colmap_model`) and its images (``images_dir``, else ``images/`` next to it as
    :func:`load_colmap` looks for it); undistort when a camera is not pinhole
    (:func:`undistort_colmap` into ``undistort_dir``, never next to the input); load with the
    hold-out ``test_every`` (3DGS: 8); and normalise (:func:`colmap_normalization`).

    Args:
        path: a model folder, or a project folder with ``sparse/0`` (or ``sparse``).
        images_dir: the images (default: found next to the model).
        scale: image resolution factor.
        test_every: every ``test_every``-th image (in name order) is held out; 0: none.
        normalize: apply the normalising similarity (False: COLMAP's frame and scale).
        undistort_dir: where to write the undistorted model and images if needed (required then).

    Returns:
        ``(colmap, recipe)``: the :class:`ColmapScene` and a JSON-able dict with ``path``
        (the model loaded: the undistorted one if any), ``images``, ``scale``, ``test_every``,
        ``transform`` (the ``(4, 4)`` similarity as nested lists, or None), ``source`` (the
        input model), ``undistorted`` (the distorted cameras, ``[]`` when none) and ``name`` (the
        project's, which the scene takes).
        :func:`reopen_colmap_project` reopens it.

    Raises:
        FileNotFoundError: if there is no model, no images folder, or a registered image is missing.
        ValueError: if a camera is distorted and no ``undistort_dir`` is given, or as
            :func:`load_colmap`.
    """
    path = Path(path)
    model = find_colmap_model(path)
    if model is None:
        raise FileNotFoundError(
            f"{path}: no COLMAP model (cameras, images, points3D as .bin or .txt) in it, in "
            "sparse/0, sparse or 0"
        )
    if images_dir is None:
        images_dir = find_images_dir(model)
        if images_dir is None:
            raise FileNotFoundError(
                f"{path}: no images/ folder next to the COLMAP model {model}; give the images folder"
            )
    images_dir = Path(images_dir)
    if not images_dir.is_dir():
        raise FileNotFoundError(f"images_dir: no such folder {images_dir}")
    distorted = distorted_cameras(model)
    source = model
    rotated = 0
    if distorted:
        if undistort_dir is None:
            raise ValueError(
                f"{model}: cameras {distorted} are distorted; give undistort_dir to undistort them"
            )
        names = [im.name for im in read_colmap_model(model, "path").images.values() if im.has_pose]
        rotated = warn_exif_rotated(images_dir, names)  # the photos themselves, not the undistorted copies
        model, images_dir = _undistort_cached(model, images_dir, Path(undistort_dir))
    try:
        with warnings.catch_warnings():
            if distorted and rotated:  # said above
                warnings.filterwarnings("ignore", message=".*EXIF orientation tag that COLMAP ignores")
            colmap = load_colmap(model, images_dir, scale=scale, test_every=test_every)
    except BaseException:
        if distorted and undistort_dir is not None:  # the undistorted copy is no use: remove it
            shutil.rmtree(undistort_dir, ignore_errors=True)
        raise
    name = colmap_project_name(source)
    colmap = colmap._replace(scene=dataclasses.replace(colmap.scene, name=name))
    transform = None
    if normalize:
        transform = colmap_normalization(colmap)
        colmap = transform_colmap(colmap, transform)
    recipe = {
        "path": str(model.resolve()),
        "images": str(images_dir.resolve()),
        "scale": float(scale),
        "test_every": int(test_every),
        "transform": transform.tolist() if transform is not None else None,
        "source": str(source.resolve()),
        "undistorted": distorted,
        "name": name,
    }
    return colmap, recipe


def reopen_colmap_project(recipe: dict[str, Any]) -> ColmapScene:
    """The scene of an :func:`open_colmap_project` recipe again, exactly (no undistortion, no new fit).

    Args:
        recipe: the recipe (``path``, ``images``, ``scale``, ``test_every``, ``transform``,
            ``name``), e.g. a run's scene reference (``open_scene``).

    Returns:
        The :class:`ColmapScene`: the recorded similarity re-applied, the project's name.
    """
    transform = recipe.get("transform")
    colmap = load_colmap(
        recipe["path"],
        recipe.get("images"),
        scale=float(recipe.get("scale", 1.0)),
        test_every=int(recipe.get("test_every", 0)),
        normalize=torch.tensor(transform, dtype=torch.float64) if transform is not None else False,
    )
    if recipe.get("name"):
        colmap = colmap._replace(scene=dataclasses.replace(colmap.scene, name=recipe["name"]))
    return colmap
