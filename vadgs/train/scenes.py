"""Scene references: how a run names its scene, one typed dataclass per kind, and how it is opened.

A run's checkpoint stores its scene as a plain dict — ``{"kind": "benchmark" | "dgp" | "colmap",
"path": ..., ...}`` — that :func:`open_scene` reopens. A new run starts from a typed reference:
:class:`BenchmarkRef`, :class:`DGPRef` or :class:`ColmapRef` (:func:`scene_ref` picks the kind of a
folder), which :func:`prepare_scene` opens and turns into the dict to store.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar

import torch

from vadgs.data.scene import Scene

__all__ = ["BenchmarkRef", "ColmapRef", "DGPRef", "SceneRef", "open_scene", "prepare_scene", "scene_ref"]


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


def _check_scale(ref: Any) -> None:
    if not isinstance(ref.path, (str, Path)) or not str(ref.path):
        raise ValueError(f"{type(ref).__name__}.path: expected a folder, got {ref.path!r}")
    object.__setattr__(ref, "path", str(ref.path))
    if not float(ref.scale) > 0:
        raise ValueError(f"{type(ref).__name__}.scale: expected > 0, got {ref.scale}")


@dataclass(frozen=True)
class BenchmarkRef:
    """A rendered benchmark scene: its folder (with ``scene.json``) and image resolution factor."""

    path: str
    scale: float = 0.5
    kind: ClassVar[str] = "benchmark"

    def __post_init__(self) -> None:
        _check_scale(self)

    def to_dict(self) -> dict[str, Any]:
        """The reference a checkpoint stores (:func:`open_scene` reopens it)."""
        return {"kind": self.kind, "path": self.path, "scale": self.scale}


@dataclass(frozen=True)
class DGPRef:
    """A DGP scene folder (``scene_*.json``): resolution, cameras (None: all), held-out frames."""

    path: str
    scale: float = 0.5
    cameras: tuple[str, ...] | None = None
    test_frames: tuple[int, ...] = ()
    kind: ClassVar[str] = "dgp"

    def __post_init__(self) -> None:
        _check_scale(self)
        if self.cameras is not None:
            object.__setattr__(self, "cameras", tuple(self.cameras))
        object.__setattr__(self, "test_frames", tuple(int(f) for f in self.test_frames))

    def to_dict(self) -> dict[str, Any]:
        """The reference a checkpoint stores (:func:`open_scene` reopens it)."""
        ref = {"kind": self.kind, "path": self.path, "scale": self.scale}
        ref["test_frames"] = list(self.test_frames)
        if self.cameras:
            ref["cameras"] = list(self.cameras)
        return ref


@dataclass(frozen=True)
class ColmapRef:
    """A COLMAP model or project folder, as :func:`vadgs.data.open_colmap_project` opens it.

    Attributes:
        path: the model folder, or a project folder with ``sparse/0`` (or ``sparse``).
        images: the images folder (None: ``images/`` next to the model).
        scale: image resolution factor.
        test_every: every ``test_every``-th image (in name order) is held out (3DGS: 8); 0: none.
        normalize: centre the cameras, put up on +z and scale to a median depth of 10 units.
    """

    path: str
    images: str | None = None
    scale: float = 1.0
    test_every: int = 8
    normalize: bool = True
    kind: ClassVar[str] = "colmap"

    def __post_init__(self) -> None:
        _check_scale(self)
        if self.test_every < 0:
            raise ValueError(f"ColmapRef.test_every: expected >= 0, got {self.test_every}")


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


def _detect_kind(path: Path) -> str:
    from vadgs.data import find_colmap_model

    if (path / "scene.json").is_file() or path.name == "scene.json":
        return "benchmark"
    if find_colmap_model(path) is None:
        raise FileNotFoundError(
            f"SCENE {path}: neither a benchmark scene (no scene.json) nor a COLMAP model "
            "(cameras, images, points3D as .bin or .txt in it, in sparse/0, sparse or 0); "
            "a DGP scene needs --dgp"
        )
    return "colmap"


def prepare_scene(ref: SceneRef, out_dir: str | Path, log: Any = None) -> tuple[Scene, dict[str, Any]]:
    """Open the scene of a new run: ``(scene, stored)``, ``stored`` the reference its checkpoint keeps.

    A COLMAP project with distorted cameras is undistorted into ``out_dir/undistorted`` (the run
    reads it from there); its normalising similarity is recorded, so :func:`open_scene` reopens
    the same scene. ``log`` (a ``print``-like callable) hears what was done to the input.
    """
    if isinstance(ref, ColmapRef):
        from vadgs.data import open_colmap_project
        from vadgs.data.normalize import similarity_scale

        if ref.images is not None and not Path(ref.images).is_dir():
            raise FileNotFoundError(f"--images {ref.images}: no such folder")
        out = Path(out_dir)
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
            log(
                f"COLMAP cameras {recipe['undistorted']} are distorted: undistorted {scene.num_views} "
                f"images with pycolmap into {out / 'undistorted'} (the run reads them from there)"
            )
        if log is not None and recipe["transform"] is not None:
            s = similarity_scale(torch.tensor(recipe["transform"]))
            log(
                f"normalised the COLMAP frame: cameras centred, up on +z, scale x{s:.4g} (median "
                "camera-to-point depth 10 units); --no-normalize keeps COLMAP's"
            )
        return scene, {"kind": "colmap", **recipe}
    if not isinstance(ref, (BenchmarkRef, DGPRef)):
        raise TypeError(f"ref: expected a BenchmarkRef, DGPRef or ColmapRef, got {type(ref).__name__}")
    stored = ref.to_dict()
    return open_scene(stored), stored
