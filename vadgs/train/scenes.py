"""Scene references: how a run names its scene, one typed dataclass per kind, and how it is opened.

A run's checkpoint stores its scene as a plain dict — ``{"kind": "benchmark" | "dgp" | "colmap",
"path": ..., ...}`` — that :func:`open_scene` reopens. A new run starts from a typed reference:
:class:`BenchmarkRef`, :class:`DGPRef` or :class:`ColmapRef` (:func:`scene_ref` picks the kind of a
folder), which :func:`prepare_scene` opens and turns into the dict to store.
"""

from __future__ import annotations

import dataclasses
import hashlib
from dataclasses import dataclass
from pathlib import Path
from typing import Any, BinaryIO, ClassVar

import torch

from vadgs.checks import (
    Checked,
    bool_field,
    checked,
    float_field,
    instance_field,
    int_field,
    ints_field,
    names_field,
)
from vadgs.data.scene import Scene

__all__ = [
    "FINGERPRINT_CHECKS",
    "BenchmarkRef",
    "ColmapRef",
    "DGPRef",
    "SceneRef",
    "file_sha256",
    "folder_kind",
    "locate_scene",
    "open_run_scene",
    "open_scene",
    "prepare_scene",
    "read_scene",
    "scene_fingerprint",
    "scene_ref",
]


def open_scene(ref: dict[str, Any]) -> Scene:
    """Load the scene a run refers to: ``{"kind": "benchmark" | "dgp" | "colmap", "path": ..., ...}``.

    ``dgp`` references may carry ``cameras`` and ``test_frames``. ``colmap`` references are the
    recipe of :func:`vadgs.data.colmap_project.open_colmap_project`, reopened by
    :func:`~vadgs.data.colmap_project.reopen_colmap_project`: ``path`` (the model used, the
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


def _folder(name: str, value: Any) -> str:
    """A folder: a non-empty ``str`` or :class:`~pathlib.Path`, stored as a ``str``."""
    if not isinstance(value, (str, Path)) or not str(value):
        raise ValueError(f"{name}: expected a folder, got {value!r}")
    return str(value)


_SCALE = float_field(0, lo_open=True)


@dataclass(frozen=True)
class BenchmarkRef(Checked):
    """A rendered benchmark scene: its folder (with ``scene.json``) and image resolution factor."""

    path: str = checked(rule=_folder)
    scale: float = checked(0.5, _SCALE)
    kind: ClassVar[str] = "benchmark"

    def to_dict(self) -> dict[str, Any]:
        """The reference a checkpoint stores (:func:`open_scene` reopens it)."""
        return {"kind": self.kind, "path": self.path, "scale": self.scale}


@dataclass(frozen=True)
class DGPRef(Checked):
    """A DGP scene folder (``scene_*.json``): resolution, cameras (None: all), held-out frames."""

    path: str = checked(rule=_folder)
    scale: float = checked(0.5, _SCALE)
    cameras: tuple[str, ...] | None = checked(None, names_field("camera names", optional=True))
    test_frames: tuple[int, ...] = checked((), ints_field("frame indices"))
    kind: ClassVar[str] = "dgp"

    def to_dict(self) -> dict[str, Any]:
        """The reference a checkpoint stores (:func:`open_scene` reopens it)."""
        ref = {"kind": self.kind, "path": self.path, "scale": self.scale}
        ref["test_frames"] = list(self.test_frames)
        if self.cameras:
            ref["cameras"] = list(self.cameras)
        return ref


@dataclass(frozen=True)
class ColmapRef(Checked):
    """A COLMAP model or project folder, as :func:`vadgs.data.open_colmap_project` opens it.

    Attributes:
        path: the model folder, or a project folder with ``sparse/0`` (or ``sparse``).
        images: the images folder (None: ``images/`` next to the model).
        scale: image resolution factor.
        test_every: every ``test_every``-th image (in name order) is held out (3DGS: 8); 0: none.
        normalize: centre the cameras, put up on +z and scale to a median depth of 10 units.
    """

    path: str = checked(rule=_folder)
    images: str | None = checked(None, instance_field(str, optional=True))
    scale: float = checked(1.0, _SCALE)
    test_every: int = checked(8, int_field(0, note=" (0: none held out)"))
    normalize: bool = checked(True, bool_field())
    kind: ClassVar[str] = "colmap"


SceneRef = BenchmarkRef | DGPRef | ColmapRef
_REFS = {cls.kind: cls for cls in (BenchmarkRef, DGPRef, ColmapRef)}


def scene_ref(path: str | Path, kind: str | None = None, **options: Any) -> SceneRef:
    """The reference of a scene folder: ``kind`` given, or found from what the folder holds.

    A folder with ``scene.json`` (or that file) is a benchmark scene, a folder with a COLMAP model
    (:func:`vadgs.data.find_colmap_model`) a COLMAP one; a DGP scene needs ``kind="dgp"``.

    Args:
        path: the scene folder.
        kind: ``"benchmark"``, ``"dgp"``, ``"colmap"`` or None (detected).
        **options: the fields of that kind's reference (``scale``, ``cameras``, ``images``, ...).

    Raises:
        FileNotFoundError: a folder of no known kind.
        ValueError: an unknown kind, or an option the kind does not have (named).

    Example:
        >>> from vadgs.data import sample_scene_path
        >>> scene_ref(sample_scene_path(), scale=0.25).kind
        'benchmark'
    """
    path = Path(path)
    if kind is None:
        kind = _detect_kind(path)
    if kind not in _REFS:
        raise ValueError(f"kind: expected one of {list(_REFS)}, got {kind!r}")
    cls = _REFS[kind]
    fields = {f.name for f in dataclasses.fields(cls)}
    bad = sorted(set(options) - fields)
    if bad:
        raise ValueError(f"{bad}: not options of a {kind} scene (its options: {sorted(fields - {'path'})})")
    return cls(str(path), **options)


def _detect_kind(path: Path, what: str = "SCENE") -> str:
    kind = folder_kind(path)
    if kind in ("benchmark", "colmap"):
        return kind
    raise FileNotFoundError(f"{what} {path}: " + _not_a_scene(path, kind))


def folder_kind(path: str | Path) -> str | None:
    """What a folder given to a command is, for its messages; None when none of these.

    ``"benchmark"`` (a ``scene.json``, or that file itself), ``"colmap"`` (a COLMAP model or
    project), ``"run"`` (a vadgs run: a checkpoint or its ``metrics.json``), ``"photos"`` (photos
    ``vadgs sfm`` takes, :data:`vadgs.data.photos.PHOTO_SUFFIXES`, in the folder itself).

    For the messages of a command given the wrong kind of folder (a run where a scene goes, photos
    where a project goes, ...).

    Example:
        >>> from vadgs.data import sample_scene_path
        >>> folder_kind(sample_scene_path())
        'benchmark'
    """
    from vadgs.data import find_colmap_model
    from vadgs.data.photos import PHOTO_SUFFIXES
    from vadgs.runfolder import is_vadgs_folder
    from vadgs.train.checkpoint import CHECKPOINT_NAME

    path = Path(path)
    if (path / "scene.json").is_file() or path.name == "scene.json":
        return "benchmark"
    if find_colmap_model(path) is not None:
        return "colmap"
    if ((path / CHECKPOINT_NAME).is_file() or (path / "metrics.json").is_file()) and is_vadgs_folder(path):
        return "run"  # by what vadgs wrote: another tool's metrics.json or checkpoint.pt is no run
    if path.is_dir() and any(p.suffix.lower() in PHOTO_SUFFIXES for p in path.iterdir()):
        return "photos"
    return None


def _not_a_scene(path: Path, kind: str | None) -> str:
    """Why ``path`` (of :func:`folder_kind` ``kind``) is no scene, and what to run instead."""
    from vadgs.data.photos import PHOTO_SUFFIXES

    if kind == "run":
        return (
            "is a vadgs run, not a scene (vadgs eval / render / export take it; "
            "vadgs train --resume continues it)"
        )
    if kind == "photos":
        photos = [p for p in path.iterdir() if p.suffix.lower() in PHOTO_SUFFIXES]
        return (
            f"a folder of {len(photos)} photos, not a scene: make a COLMAP project of them first, "
            f"vadgs sfm {path} --out PROJECT, then vadgs train PROJECT"
        )
    return (
        "neither a benchmark scene (no scene.json) nor a COLMAP model "
        "(cameras, images, points3D as .bin or .txt in it, in sparse/0, sparse or 0); "
        "a DGP scene needs --dgp"
    )


def read_scene(ref: SceneRef, validate: str = "headers") -> Scene:
    """Open a scene reference as it is on disk, writing nothing (``vadgs check``, ``vadgs visibility``).

    Unlike :func:`prepare_scene` a COLMAP model with distorted cameras is not undistorted: it is
    read with its pinhole part (:func:`~vadgs.data.load_colmap` warns that the distortion is
    ignored); its normalisation (``ref.normalize``) and split (``ref.test_every``) apply.

    Args:
        ref: the reference (:func:`scene_ref`).
        validate: the loader's content checks: ``"headers"``, ``"full"`` or ``"none"`` (then
            missing files are not checked either: :func:`~vadgs.data.validate_scene` reports them).

    Raises:
        FileNotFoundError, ValueError: as the kind's loader.

    Example:
        >>> from vadgs.data import sample_scene_path
        >>> read_scene(scene_ref(sample_scene_path(), scale=0.25)).num_views
        24
    """
    from vadgs.data import find_colmap_model, load_colmap, load_dgp, load_scene

    files = validate != "none"
    if isinstance(ref, BenchmarkRef):
        return load_scene(ref.path, scale=ref.scale, check_files=files, validate=validate)
    if isinstance(ref, DGPRef):
        return load_dgp(
            ref.path,
            ref.cameras,
            scale=ref.scale,
            test_frames=ref.test_frames,
            check_files=files,
            validate=validate,
        )
    if not isinstance(ref, ColmapRef):
        raise TypeError(f"ref: expected a BenchmarkRef, DGPRef or ColmapRef, got {type(ref).__name__}")
    model = find_colmap_model(ref.path)
    if model is None:
        raise FileNotFoundError(f"{ref.path}: no COLMAP model (cameras, images, points3D as .bin or .txt)")
    colmap = load_colmap(
        model,
        ref.images,
        ref.scale,
        check_files=files,
        validate=validate,
        test_every=ref.test_every,
        normalize=ref.normalize,
    )
    return colmap.scene


def prepare_scene(ref: SceneRef, out_dir: str | Path, log: Any = None) -> tuple[Scene, dict[str, Any]]:
    """Open the scene of a new run: ``(scene, stored)``, ``stored`` the reference its checkpoint keeps.

    A COLMAP project with distorted cameras is undistorted into ``out_dir/undistorted`` (the run
    reads it from there); its normalising similarity is recorded, so :func:`open_scene` reopens
    the same scene. ``log`` (a ``print``-like callable) hears what was done to the input.

    ``stored`` names the scene by absolute paths and carries ``run_dir`` (the run folder,
    absolute: paths inside it follow the run when it moves) and ``fingerprint``
    (:func:`scene_fingerprint`), which :func:`open_run_scene` checks when the run is reopened.
    """
    out = Path(out_dir)
    if isinstance(ref, ColmapRef):
        from vadgs.data import open_colmap_project
        from vadgs.data.normalize import similarity_scale

        if ref.images is not None and not Path(ref.images).is_dir():
            raise FileNotFoundError(f"--images {ref.images}: no such folder")
        colmap, recipe = open_colmap_project(
            ref.path,
            ref.images,
            scale=ref.scale,
            test_every=ref.test_every,
            normalize=ref.normalize,
            undistort_dir=out / "undistorted",
        )
        scene = colmap.scene
        if log is not None and recipe["undistorted"]:
            kept = Path(recipe["source"]).parent.parent / ".vadgs-undistorted"  # a vadgs sfm project's
            kept_note = f"; pycolmap's copy kept in {kept} for the next runs" if kept.is_dir() else ""
            log(
                f"COLMAP cameras {recipe['undistorted']} are distorted: undistorted {scene.num_views} "
                f"images with pycolmap into {out / 'undistorted'} (the run reads them from there{kept_note})"
            )
        if log is not None and recipe["transform"] is not None:
            s = similarity_scale(torch.tensor(recipe["transform"]))
            log(
                f"normalised the COLMAP frame: cameras centred, up on +z, scale x{s:.4g} (median "
                "camera-to-point depth 10 units); --no-normalize keeps COLMAP's"
            )
        stored = {"kind": "colmap", **recipe}
    elif isinstance(ref, (BenchmarkRef, DGPRef)):
        stored = ref.to_dict()
        stored["path"] = str(Path(ref.path).resolve())
        scene = open_scene(stored)
    else:
        raise TypeError(f"ref: expected a BenchmarkRef, DGPRef or ColmapRef, got {type(ref).__name__}")
    stored["run_dir"] = str(out.resolve())
    stored["fingerprint"] = scene_fingerprint(stored, scene)
    return scene, stored


# ---------------------------------------------------------------------------------------------------
# a run's scene: fingerprint, where it is, reopening it

_COLMAP_FILES = ("cameras", "images", "points3D", "rigs", "frames")


def _metadata_files(ref: dict[str, Any]) -> list[Path]:
    """The files that describe a scene (hashed whole by :func:`scene_fingerprint`)."""
    kind, path = ref.get("kind", "benchmark"), Path(ref["path"])
    if kind == "benchmark":
        return [path if path.name == "scene.json" else path / "scene.json"]
    if kind == "dgp":
        return [path] if path.is_file() else sorted(path.glob("scene*.json"))
    return [path / f"{n}.{e}" for n in _COLMAP_FILES for e in ("bin", "txt") if (path / f"{n}.{e}").is_file()]


FINGERPRINT_CHECKS = (
    "the metadata files and the test views' image, depth and instance files whole; the other "
    "files by name, size and 12 KiB of their bytes (start, middle, end)"
)
"""What :func:`scene_fingerprint` reads of a scene (what ``eval.json`` says it checked)."""

_SAMPLE = 4096  # bytes read at each of a file's start, middle and end


def file_sha256(fh: BinaryIO) -> bytes:
    """The SHA-256 of a binary file's bytes from its position on (``hashlib.file_digest``: Python 3.11+)."""
    h = hashlib.sha256()
    for block in iter(lambda: fh.read(1 << 20), b""):
        h.update(block)
    return h.digest()


def scene_fingerprint(ref: dict[str, Any], scene: Scene) -> str:
    """A content fingerprint of a scene, wherever it lies: 16 hex digits of a SHA-256.

    Cheap: the metadata files (``scene.json``, the DGP scene JSON, the COLMAP model files of
    ``ref["path"]``) are hashed whole, and so are the test views' images, depth and instance
    maps (what an evaluation scores); the training views' files and the frames' LiDAR sweeps by
    name, size and 12 KiB of their bytes (:data:`FINGERPRINT_CHECKS`). Two copies of one scene have the same
    fingerprint (modification times are not read); another scene, or one whose metadata or
    files changed, another one.

    Args:
        ref: the scene's reference (``kind``, ``path``), as :func:`open_scene` takes it.
        scene: the scene it opened.

    Example:
        >>> from vadgs.data import sample_scene_path
        >>> ref = {"kind": "benchmark", "path": str(sample_scene_path()), "scale": 0.25}
        >>> len(scene_fingerprint(ref, open_scene(ref)))
        16
    """
    h = hashlib.sha256(str(ref.get("kind", "benchmark")).encode())
    for f in _metadata_files(ref):
        h.update(f"\n{f.name}\n".encode())
        with f.open("rb") as fh:
            h.update(file_sha256(fh))

    def add(p: Path | None, whole: bool = False) -> None:
        if p is None:
            h.update(b"-;")
            return
        size = p.stat().st_size if p.is_file() else -1
        h.update(f"{p.name}:{size};".encode())
        if size > 0:
            with p.open("rb") as fh:
                if whole or size <= 3 * _SAMPLE:
                    h.update(file_sha256(fh))
                    return
                for at in (0, size // 2 - _SAMPLE // 2, size - _SAMPLE):
                    fh.seek(at)
                    h.update(fh.read(_SAMPLE))

    test = set(scene.test_views)
    for v in scene.views:
        for p in (v.image, v.depth, v.instances):
            add(p, whole=v.index in test)
    for frame in scene.frames:
        add(frame.lidar)
    return h.hexdigest()[:16]


def _scene_exists(kind: str, path: Path) -> bool:
    from vadgs.data import find_colmap_model

    if kind == "benchmark":
        return (path / "scene.json").is_file() or (path.name == "scene.json" and path.is_file())
    if kind == "dgp":
        return path.exists()
    return find_colmap_model(path) is not None


def _hint(flag: str) -> str:
    """How to name a moved scene: ``pass --scene FOLDER`` (a flag) or ``give SCENE`` (an argument)."""
    return f"pass {flag} FOLDER" if flag.startswith("--") else f"give {flag}"


def locate_scene(
    ref: dict[str, Any], run_dir: str | Path, scene: str | Path | None = None, flag: str = "--scene"
) -> dict[str, Any]:
    """A run's scene reference with its paths as they are now (checked to exist).

    - Paths inside the run folder where it was trained (``ref["run_dir"]``: a COLMAP run's
      undistorted copy) are taken inside ``run_dir``, where the run is now.
    - ``scene`` (``--scene``): the scene's folder, for a run whose scene moved; it must be of the
      run's kind (:func:`scene_ref` decides). A COLMAP run reads the model found there and the
      ``images/`` next to it (an undistorted copy inside the run stays the run's).

    Args:
        ref: the stored reference (``Checkpoint.scene_ref``).
        run_dir: the run folder now.
        scene: the scene's folder now, or None (the recorded one).
        flag: the argument that names the scene, for the messages.

    Raises:
        ValueError: no scene reference stored (a run of an in-memory scene), or ``scene`` of
            another kind than the run's.
        FileNotFoundError: the scene is not where the reference says; the message says where it
            looked and names ``flag``.
    """
    run_dir = Path(run_dir).resolve()
    if not ref.get("path"):
        raise ValueError(
            f"run {run_dir}: no scene reference stored (trained on an in-memory scene); "
            "open it with Trainer.from_checkpoint(..., scene=)"
        )
    located = dict(ref)
    kind = str(located.get("kind", "benchmark"))
    was = Path(ref["run_dir"]) if ref.get("run_dir") else None
    keys = ("path", "images")
    for key in keys:
        value = Path(located[key]) if located.get(key) else None
        if value is None or not value.is_absolute():
            continue
        if was is not None and was != run_dir and value.is_relative_to(was):
            located[key] = str(run_dir / value.relative_to(was))
    if scene is not None:
        given = Path(scene)
        found = "dgp" if kind == "dgp" and given.exists() else _detect_kind(given, flag)  # as scene_ref
        if found != kind:
            raise ValueError(
                f"{flag} {given}: a {found} scene, but the run {run_dir} was trained on a {kind} scene"
            )
        given = given.resolve()
        if kind != "colmap":
            located["path"] = str(given)
        else:
            from vadgs.data import find_colmap_model
            from vadgs.data.colmap import find_images_dir

            model = find_colmap_model(given)
            if model is None:  # found as a COLMAP project just above: gone since
                raise FileNotFoundError(f"{flag} {given}: expected a COLMAP model in it, found none")
            located["source"] = str(model)
            if not Path(located["path"]).is_relative_to(run_dir):  # not an undistorted copy in the run
                located["path"] = str(model)
                images = find_images_dir(model)
                located["images"] = str(images) if images is not None else located.get("images")
    located["run_dir"] = str(run_dir)  # where the paths above were found: a resumed run records it
    path = Path(located["path"])
    if not _scene_exists(kind, path):
        what = "--scene" if scene is not None else "recorded"
        raise FileNotFoundError(
            f"run {run_dir}: its {kind} scene is not at {path} ({what}; moved or deleted?); "
            f"{_hint(flag)} to point the run at its data"
        )
    if kind == "colmap" and located.get("images") and not Path(located["images"]).is_dir():
        raise FileNotFoundError(
            f"run {run_dir}: the images of its COLMAP scene are not at {located['images']} (moved or "
            f"deleted?); {_hint(flag)} (the project, with images/) to point the run at its data"
        )
    return located


def open_run_scene(
    ref: dict[str, Any], run_dir: str | Path, scene: str | Path | None = None, flag: str = "--scene"
) -> tuple[Scene, dict[str, Any]]:
    """Reopen a run's scene, from any current folder: ``(scene, located)``.

    :func:`locate_scene` finds it (``scene``: the folder it moved to); its fingerprint is then
    compared with the one the run recorded (a ``Trainer`` given a loaded scene records none).
    ``located`` is the reference as used, with the fingerprint of what was opened: what a
    resumed run records and what ``eval.json`` names.

    Raises:
        ValueError: the scene found is not the run's (its fingerprint differs; the message names
            both scenes and both fingerprints), or as :func:`locate_scene`.
        FileNotFoundError: as :func:`locate_scene`.
    """
    located = locate_scene(ref, run_dir, scene, flag)
    opened = open_scene(located)
    now = scene_fingerprint(located, opened)
    recorded = ref.get("fingerprint")
    if recorded and now != recorded:
        raise ValueError(
            f"scene {located['path']} (fingerprint {now}) is not the scene run {Path(run_dir)} was "
            f"trained on ({ref['path']}, fingerprint {recorded}): another scene or changed files; "
            f"{_hint(flag)} with the run's own data"
        )
    located["fingerprint"] = now
    return opened, located
