"""The checks behind :func:`~vadgs.data.validate_scene`: intrinsics, rigid poses, the split, and files.

:func:`check_scene` checks a loaded :class:`~vadgs.data.Scene` (from any loader) and returns a
:class:`ValidationReport`, one row per check. Two levels:

- **headers** (the default, run by every loader that takes ``validate=``): metadata
  (``K`` finite with positive focal lengths and last row ``(0, 0, 1)``; every pose rigid: an
  orthonormal rotation with determinant +1 and last row ``(0, 0, 0, 1)`` within
  :data:`RIGID_TOLERANCE`; the split's frames unique and in the scene) and each file's header:
  a PNG's size and mode read without decoding, an ``.npz``'s keys, shapes and dtypes read from
  the array headers without decompressing, and the total LiDAR point count (an error when every
  LiDAR file is empty). The test views' depth maps are decoded in full (finite, non-negative):
  they are read only at the end of a training run, so a fault there would otherwise surface
  after the whole run; they are a quarter of the views and decode in about a millisecond each.
- **full** (``vadgs check SCENE --full``): also decodes every image, depth map, instance map and
  LiDAR sweep and checks their values (finite depth; finite points within
  :data:`LIDAR_MAX_RANGE_M` of their sensor, :func:`check_lidar_points`), and the SfM points of a
  COLMAP scene (finite). Sweeps a loader reads from its own files (Waymo's parquet) are decoded
  through the scene at this level; LiDAR files that are not ``.npz`` (nuScenes' ``.pcd.bin``) at
  both levels.

The single checks (:func:`check_rigid`, :func:`check_split`; intrinsics:
:func:`vadgs.checks.check_intrinsics`) are also
what the readers run on the metadata they parse. Imports go one way: :mod:`vadgs.data.scene` ←
this module ← the readers ← :mod:`vadgs.data.validate`.

Example:
    >>> pose = torch.eye(4); pose[:3, :3] *= 1.1  # scaled: not rigid
    >>> check_rigid(pose, "pose")
    Traceback (most recent call last):
    ...
    ValueError: pose: expected a rigid transform (orthonormal rotation, det +1), got max |R^T R - I| = 0.21...
"""

from __future__ import annotations

import functools
import zipfile
from collections.abc import Callable
from pathlib import Path
from typing import NamedTuple

import torch
from PIL import Image

from vadgs.checks import check_intrinsics
from vadgs.data.images import SUPPORTED_MODES, read_image
from vadgs.data.scene import Scene, npz_headers, read_depth

__all__ = [
    "LIDAR_MAX_RANGE_M",
    "RIGID_TOLERANCE",
    "ValidationReport",
    "ValidationRow",
    "check_lidar_points",
    "check_png",
    "check_rigid",
    "check_scene",
    "check_split",
]

#: Absolute tolerance on ``R^T R - I``, ``det R - 1`` and the last row of a rigid transform.
#: Poses stored with 6 decimals are off by about 1e-6; a 1 % scale is off by 0.02.
RIGID_TOLERANCE = 1e-3
#: No LiDAR point lies farther from its sensor (metres): the longest-range automotive sensors
#: reach 250-500 m. A point beyond is what a corrupt file decodes into (random float32 bytes are
#: up to 3.4e38).
LIDAR_MAX_RANGE_M = 1000.0
_INSTANCE_MODES = ("I;16", "I;16B", "I;16L", "I", "L")  # what an instance map's PNG may hold


class ValidationRow(NamedTuple):
    """One check: ``status`` is ``"ok"`` or ``"error"``; ``file`` is empty for metadata."""

    item: str
    file: str
    status: str
    message: str


class ValidationReport(NamedTuple):
    """What :func:`check_scene` (and :func:`~vadgs.data.validate_scene`) found.

    Attributes:
        scene: the scene's name or folder.
        rows: the checks in order, see :class:`ValidationRow`.
        full: whether every file was decoded.
    """

    scene: str
    rows: tuple[ValidationRow, ...]
    full: bool = False

    @property
    def errors(self) -> list[ValidationRow]:
        """The rows whose status is ``"error"``."""
        return [r for r in self.rows if r.status != "ok"]

    @property
    def ok(self) -> bool:
        """True when no check failed."""
        return not self.errors

    def raise_if_errors(self) -> None:
        """Raise a :class:`ValueError` naming the first failed checks (and how many there are)."""
        errs = self.errors
        if not errs:
            return
        shown = "; ".join(_row_text(r) for r in errs[:3])
        more = f" (and {len(errs) - 3} more)" if len(errs) > 3 else ""
        raise ValueError(
            f"scene {self.scene}: {len(errs)} problem(s): {shown}{more}; `vadgs check` lists them all"
        )

    def format_table(self) -> str:
        """The rows as an aligned text table (``status  item  file  message``)."""
        head = ("status", "check", "file", "message")
        lines = [head] + [(r.status, r.item, r.file or "-", r.message) for r in self.rows]
        widths = [max(len(line[i]) for line in lines) for i in range(3)]
        out = ["  ".join(c.ljust(w) for c, w in zip(line[:3], widths)) + "  " + line[3] for line in lines]
        out.insert(1, "  ".join("-" * w for w in widths) + "  " + "-" * 7)
        return "\n".join(s.rstrip() for s in out)


def _row_text(r: ValidationRow) -> str:
    return f"{r.file}: {r.item}: {r.message}" if r.file else f"{r.item}: {r.message}"


def _fmt(x: float) -> str:
    return f"{x:.3g}"


def check_rigid(T: torch.Tensor, what: str, tol: float = RIGID_TOLERANCE) -> None:
    """Raise a :class:`ValueError` unless ``T (4, 4)`` is a rigid transform within ``tol``.

    Rigid: finite, last row ``(0, 0, 0, 1)``, rotation block orthonormal with determinant +1
    (no scale, shear or reflection).
    """
    T = torch.as_tensor(T, dtype=torch.float64)
    if tuple(T.shape) != (4, 4):
        raise ValueError(f"{what}: expected shape (4, 4), got {tuple(T.shape)}")
    if not bool(torch.isfinite(T).all()):
        raise ValueError(f"{what}: expected finite values, got a non-finite entry")
    row = T[3] - torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=T.dtype)
    if float(row.abs().max()) > tol:
        raise ValueError(
            f"{what}: expected last row (0, 0, 0, 1), got {tuple(round(v, 6) for v in T[3].tolist())}"
        )
    R = T[:3, :3]
    err = float((R.T @ R - torch.eye(3, dtype=T.dtype)).abs().max())
    if err > tol:
        raise ValueError(
            f"{what}: expected a rigid transform (orthonormal rotation, det +1), "
            f"got max |R^T R - I| = {_fmt(err)} (tolerance {tol:g})"
        )
    det = float(torch.linalg.det(R))
    if abs(det - 1) > tol:
        raise ValueError(f"{what}: expected a rotation with det +1, got det {_fmt(det)} (a reflection)")


# ---------------------------------------------------------------------------------------------------


class _Collector:
    def __init__(self) -> None:
        self.rows: list[ValidationRow] = []

    def run(self, item: str, file: Path | str | None, fn: Callable[[], str | None]) -> bool:
        """Run one check; a raised ValueError / OSError becomes an error row."""
        try:
            msg = fn()
        except FileNotFoundError as e:
            self.rows.append(ValidationRow(item, str(file or ""), "error", f"missing file ({e})"))
            return False
        except (ValueError, OSError, KeyError, zipfile.BadZipFile, EOFError) as e:
            text = str(e)
            if file is not None and text.startswith(f"{file}: "):
                text = text[len(f"{file}: ") :]
            if text.startswith(f"{item}: "):
                text = text[len(f"{item}: ") :]
            self.rows.append(ValidationRow(item, str(file or ""), "error", text))
            return False
        if msg is not None:
            self.rows.append(ValidationRow(item, str(file or ""), "ok", msg))
        return True


def _expected_file_size(size: tuple[int, int], scale: float) -> str:
    h, w = size
    if scale == 1.0:
        return f"{w}x{h}"
    return f"{round(w / scale)}x{round(h / scale)} (the scene's {w}x{h} at scale {scale:g})"


def _size_matches(file_wh: tuple[int, int], size: tuple[int, int], scale: float) -> bool:
    fw, fh = file_wh
    return (round(fh * scale), round(fw * scale)) == tuple(size)


def check_png(
    path: Path, size: tuple[int, int], scale: float, modes: tuple[str, ...] | None, full: bool
) -> None:
    """An image file's size and mode; ``full``: decoded (colour images as the loaders decode them).

    ``modes=None``: a colour image, of any mode :func:`read_image` reads.
    """
    if not path.is_file():
        raise FileNotFoundError(path)
    try:
        with Image.open(path) as im:
            wh, mode = im.size, im.mode
            if full and modes is not None:
                im.load()
    except (OSError, SyntaxError, ValueError, Image.DecompressionBombError) as e:
        nbytes = path.stat().st_size
        what = "an empty file (0 bytes)" if nbytes == 0 else f"{type(e).__name__}: {e}"
        raise ValueError(f"not a decodable image ({what})") from None
    if not _size_matches(wh, size, scale):
        raise ValueError(f"expected size {_expected_file_size(size, scale)} (W x H), got {wh[0]}x{wh[1]}")
    if modes is not None and mode not in modes:
        raise ValueError(f"expected an image of mode {'/'.join(modes)}, got mode {mode}")
    if modes is None and mode not in SUPPORTED_MODES:
        raise ValueError(f"image mode {mode!r} is not read; expected one of {', '.join(SUPPORTED_MODES)}")
    if full and modes is None:
        try:
            read_image(path)  # the colour image as training reads it (16-bit, palette, alpha, ...)
        except ValueError as e:
            raise ValueError(str(e).removeprefix(f"{path}: ")) from None


def _check_depth(path: Path, size: tuple[int, int], scale: float, full: bool) -> None:
    if not path.is_file():
        raise FileNotFoundError(path)
    heads = npz_headers(path)
    if "depth" not in heads:
        raise ValueError(f"expected key 'depth', got keys {sorted(heads)}")
    shape, dtype = heads["depth"]
    if len(shape) != 2 or not _size_matches((shape[1], shape[0]), size, scale):
        h, w = size
        raise ValueError(
            f"depth: expected shape (H, W) = ({round(h / scale)}, {round(w / scale)}), got {shape}"
        )
    if dtype.kind != "f":
        raise ValueError(f"depth: expected a floating dtype, got {dtype}")
    if full:
        read_depth(path)


def _lidar_count(path: Path) -> int | None:
    """The point count from an ``.npz``'s headers; None for another format (decoded instead)."""
    if not path.is_file():
        raise FileNotFoundError(path)
    if path.suffix != ".npz":
        return None
    heads = npz_headers(path)
    if "points" in heads:  # the benchmark format
        shape, dtype = heads["points"]
        if len(shape) != 2 or shape[1] != 3 or dtype.kind != "f":
            raise ValueError(f"points: expected (N, 3) floating, got shape {shape} dtype {dtype}")
        n = shape[0]
        if "instance" in heads:
            ishape, idtype = heads["instance"]
            if ishape != (n,) or idtype.kind not in "iu":
                raise ValueError(f"instance: expected ({n},) integer, got shape {ishape} dtype {idtype}")
        if "origin" in heads and heads["origin"][0] != (3,):
            raise ValueError(f"origin: expected shape (3,), got {heads['origin'][0]}")
        return n
    if "data" in heads:  # DGP point clouds: (N, >= 3) X, Y, Z, ...
        shape, _ = heads["data"]
        if len(shape) != 2 or shape[1] < 3:
            raise ValueError(f"data: expected (N, >=3) X, Y, Z, ..., got shape {shape}")
        return shape[0]
    raise ValueError(f"expected key 'points' (or DGP 'data'), got keys {sorted(heads)}")


def check_scene(scene: Scene, full: bool = False, tolerance: float = RIGID_TOLERANCE) -> ValidationReport:
    """Check a loaded scene's metadata and files; see the module docstring for what each level reads.

    :func:`~vadgs.data.validate_scene` calls it (and also takes a scene folder); the loaders call
    it through :func:`~vadgs.data.assemble.assemble_scene`.

    Args:
        scene: a loaded :class:`~vadgs.data.Scene` (any loader).
        full: decode every file and check its values (``vadgs check --full``).
        tolerance: of the rigid-pose check (:func:`check_rigid`).

    Returns:
        The :class:`ValidationReport` (never raises for a bad scene: failures are rows).
    """
    col = _Collector()
    name = str(scene.root) if scene.root is not None else scene.name

    # -- metadata -------------------------------------------------------------------------------------
    for cam in scene.cameras_info.values():

        def camera(c=cam) -> str:
            check_intrinsics(c.K, f"cameras.{c.name}.K", pinhole=True)
            (h, w), fx, fy = c.image_size, float(c.K[0, 0]), float(c.K[1, 1])
            return f"fx={fx:.1f} fy={fy:.1f}, {w}x{h}"

        col.run(f"cameras.{cam.name}.K", None, camera)

    given: list[tuple[str, torch.Tensor | None]] = []
    given += [(f"cameras.{c.name}.cam_to_ego", c.cam_to_ego) for c in scene.cameras_info.values()]
    given += [(f"frame {f.index}.ego_to_world", f.ego_to_world) for f in scene.frames]
    given += [(f"view {v.index} ({v.camera}@{v.frame}).cam_to_world", v.cam_to_world) for v in scene.views]
    for tid, t in scene.tracks.items():
        given += [
            (f"track {tid}.object_to_world[frame {scene.frames[i].index}]", t.object_to_world[i])
            for i in range(len(scene.frames))
            if bool(t.valid[i])
        ]
    poses = [(w, p) for w, p in given if p is not None]
    bad_pose = [not col.run(w, None, functools.partial(check_rigid, p, w, tolerance)) for w, p in poses]
    if not any(bad_pose):
        col.rows.append(ValidationRow("poses", "", "ok", f"{len(poses)} rigid (tolerance {tolerance:g})"))

    frame_ids = [f.index for f in scene.frames]
    for key, frames in (("train_frames", scene.train_frames), ("test_frames", scene.test_frames)):

        def split(k: str = key, fr: list[int] = frames) -> str:
            check_split(fr, frame_ids, f"split.{k}")
            return f"{len(fr)} frames"

        col.run(f"split.{key}", None, split)

    # -- files ----------------------------------------------------------------------------------------
    s = float(scene.scale)
    test = set(scene.test_views)
    counts = {"images": 0, "depth": 0, "instances": 0}
    failed = {"images": 0, "depth": 0, "instances": 0}
    for v in scene.views:
        size = scene.image_size(v.index)
        if v.image is not None:
            counts["images"] += 1
            failed["images"] += not col.run(
                "image", v.image, functools.partial(check_png, v.image, size, s, None, full)
            )
        if v.depth is not None:
            counts["depth"] += 1
            decode = full or v.index in test
            failed["depth"] += not col.run(
                "depth", v.depth, functools.partial(_check_depth, v.depth, size, s, decode)
            )
        if v.instances is not None:
            counts["instances"] += 1
            failed["instances"] += not col.run(
                "instances", v.instances,
                functools.partial(check_png, v.instances, size, s, _INSTANCE_MODES, full),
            )  # fmt: skip
    for kind, n in counts.items():
        if n and not failed[kind]:
            how = "decoded" if full else ("headers" if kind != "depth" else "headers; test views decoded")
            col.rows.append(ValidationRow(kind, "", "ok", f"{n} files ({how})"))

    # frames whose LiDAR is a file, and (full) those a loader reads from its own files (Waymo)
    lidar: list[tuple[int, Path | None]] = [
        (f.index, f.lidar)
        for f in scene.frames
        if f.lidar is not None or (full and scene.lidar_loader is not None)
    ]
    if lidar:
        total, good = 0, 0
        for frame, p in lidar:
            box: dict[str, int] = {}

            def one(frame: int = frame, p: Path | None = p, box: dict = box) -> None:
                n = _lidar_count(p) if p is not None else None
                if full or n is None:
                    lf = scene.lidar(frame)
                    n = len(lf.points)
                    # a benchmark .npz without 'origin' reads as (0, 0, 0): its distances mean nothing
                    heads = npz_headers(p) if p is not None and p.suffix == ".npz" else {}
                    has_origin = "points" not in heads or "origin" in heads
                    check_lidar_points(lf.points, lf.origin if has_origin else None)
                box["n"] = n

            if col.run(f"lidar (frame {frame})", p, one):
                good += 1
                total += box["n"]
        if good == len(lidar):
            if total == 0:
                col.rows.append(ValidationRow(
                    "lidar", "", "error",
                    f"all {len(lidar)} LiDAR files are empty (0 points): no points to initialise from",
                ))  # fmt: skip
            else:
                col.rows.append(ValidationRow("lidar", "", "ok", f"{len(lidar)} files, {total} points"))
    if full and scene.sfm_points is not None:

        def sfm(pts: torch.Tensor = scene.sfm_points.points) -> str:
            bad = ~torch.isfinite(pts)
            if bool(bad.any()):
                raise ValueError(
                    f"expected finite points, got {int(bad.any(-1).sum())} non-finite of {len(pts)}"
                )
            return f"{len(pts)} points"

        col.run("sfm_points", None, sfm)
    return ValidationReport(name, tuple(col.rows), full)


def check_lidar_points(
    points: torch.Tensor,
    origin: torch.Tensor | None,
    what: str = "points",
    max_range: float = LIDAR_MAX_RANGE_M,
) -> None:
    """Raise a :class:`ValueError` if a sweep has non-finite points or points beyond ``max_range``.

    Args:
        points: ``(N, 3)`` points.
        origin: ``(3,)`` the sensor's position in the same frame, or None (only finiteness is
            checked: a world frame may lie anywhere).
        what: what the error calls the points.
        max_range: metres (:data:`LIDAR_MAX_RANGE_M`).

    Example:
        >>> check_lidar_points(torch.tensor([[1.0, 2.0, 3.0], [2.5e38, 0.0, 0.0]]), torch.zeros(3))
        Traceback (most recent call last):
        ...
        ValueError: points: 1 of 2 points lie more than 1000 m from the sensor (up to 2.5e+38 m); ...
    """
    bad = ~torch.isfinite(points)
    if bool(bad.any()):
        raise ValueError(
            f"{what}: expected finite values, got {int(bad.any(-1).sum())} non-finite points of {len(points)}"
        )
    if origin is None or len(points) == 0:
        return
    dist = torch.linalg.vector_norm(points.double() - origin.double(), dim=-1)
    far = dist > max_range
    if bool(far.any()):
        raise ValueError(
            f"{what}: {int(far.sum())} of {len(points)} points lie more than {max_range:g} m from the sensor "
            f"(up to {float(dist.max()):.3g} m); the file is corrupt"
        )


def check_split(frames: list[int], frame_ids: list[int], what: str) -> None:
    """Raise a :class:`ValueError` if ``frames`` has duplicates or frames not in ``frame_ids``."""
    seen: set[int] = set()
    dup = sorted({f for f in frames if f in seen or seen.add(f)})  # type: ignore[func-returns-value]
    if dup:
        raise ValueError(f"{what}: expected unique frame indices, got duplicates {dup[:5]}")
    known = set(frame_ids)
    unknown = [f for f in frames if f not in known]
    if unknown:
        lo, hi = min(frame_ids), max(frame_ids)
        raise ValueError(
            f"{what}: frame(s) {unknown[:5]} not in the scene (it has {len(frame_ids)} frames, {lo}..{hi})"
        )
