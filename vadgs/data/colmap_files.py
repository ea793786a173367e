"""Checks of a COLMAP model and its images *before* pycolmap's C++ code works on them.

pycolmap reads a model with ``CHECK`` macros whose text names neither the file nor the record
(``Check failed: point2D.point3D_id == point3D_id (137 vs. 99)`` for a truncated
``points3D.bin``), and its undistorter aborts the process (exit 134, a C++ stack) on an image of
the wrong size or two images of the same name, and fills what it cannot decode of a truncated
image with grey. These functions find such faults first and raise one :class:`ValueError` naming
the file:

- :func:`diagnose_model_files` walks the binary files (``cameras.bin``, ``images.bin``,
  ``points3D.bin``: record by record, with the sizes COLMAP's writer uses) or the text files
  (the number of fields per line) and says which file is truncated or malformed, and where; it
  runs only when pycolmap failed, to name the file in the message.
- :func:`check_reconstruction` checks what pycolmap read: image names (relative, no ``..``, no
  duplicates: a name becomes a path under the images folder and under the undistorted copy),
  finite poses with unit quaternions (pycolmap keeps a zero quaternion, which then reads as the
  identity rotation), cameras of positive size with finite parameters.
- :func:`check_colmap_images` decodes every registered image in full and compares its size with
  its camera's, so that a truncated or 0-byte file is reported under its own path whatever the
  camera model.
"""

from __future__ import annotations

import math
import struct
from pathlib import Path, PurePosixPath, PureWindowsPath
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:  # imported where used: pycolmap is slow to import
    import pycolmap

__all__ = [
    "check_colmap_images",
    "check_image_name",
    "check_reconstruction",
    "diagnose_model_files",
    "diagnose_references",
]

_QUAT_TOLERANCE = 1e-3  # |‖q‖ - 1| accepted (COLMAP writes unit quaternions to 17 digits)


def check_image_name(name: str, what: str) -> str:
    r"""``name`` if it is a safe relative image path (it becomes ``IMAGES/name`` and ``RUN/.../name``).

    Raises:
        ValueError: for an empty name, an absolute path (``/x``, ``C:\x``), a ``..`` component or
            a backslash, naming ``what``.

    Example:
        >>> check_image_name("front/016.png", "image 1")
        'front/016.png'
        >>> check_image_name("../../etc/x.png", "image 1")
        Traceback (most recent call last):
        ...
        ValueError: image 1: expected a relative image path inside the images folder, got '../../etc/x.png'
    """
    parts = PurePosixPath(name).parts
    if (
        not name
        or "\\" in name
        or "\0" in name
        or PurePosixPath(name).is_absolute()
        or PureWindowsPath(name).drive
        or ".." in parts
    ):
        raise ValueError(f"{what}: expected a relative image path inside the images folder, got {name!r}")
    return name


def check_reconstruction(rec: pycolmap.Reconstruction, sparse_dir: Path) -> None:
    """Check a :class:`pycolmap.Reconstruction` before any other pycolmap call uses it.

    Raises:
        ValueError: naming the model folder and the image or camera: an unsafe or duplicate image
            name, a non-finite pose, a quaternion that is not of unit norm (zero), an image of an
            unknown camera, a camera of non-positive size or with non-finite parameters, a 3D
            point with non-finite coordinates (named with the ``points3D`` file).
    """
    for cid, cam in rec.cameras.items():
        params = np.asarray(cam.params, dtype=np.float64)
        if int(cam.width) <= 0 or int(cam.height) <= 0:
            raise ValueError(
                f"{sparse_dir}: camera {cid}: expected a positive size, got {cam.width}x{cam.height}"
            )
        if not np.isfinite(params).all():
            raise ValueError(f"{sparse_dir}: camera {cid}: expected finite parameters, got {params.tolist()}")
    seen: dict[str, int] = {}
    for iid, im in sorted(rec.images.items()):
        what = f"{sparse_dir}: image {iid}"
        check_image_name(im.name, f"{what} name")
        if im.name in seen:
            raise ValueError(
                f"{sparse_dir}: images {seen[im.name]} and {iid}: expected unique names, both are {im.name!r}"
            )
        seen[im.name] = iid
        if im.camera_id not in rec.cameras:
            raise ValueError(f"{what} {im.name!r}: camera {im.camera_id} is not in the model")
        if not im.has_pose:
            continue
        cfw = im.cam_from_world
        cfw = cfw() if callable(cfw) else cfw
        q = np.asarray(cfw.rotation.quat, dtype=np.float64)
        t = np.asarray(cfw.translation, dtype=np.float64)
        if not (np.isfinite(q).all() and np.isfinite(t).all()):
            raise ValueError(
                f"{what} {im.name!r}: cam_from_world: expected finite values, got quaternion "
                f"{q.tolist()}, translation {t.tolist()}"
            )
        norm = float(np.linalg.norm(q))
        if abs(norm - 1.0) > _QUAT_TOLERANCE:
            raise ValueError(
                f"{what} {im.name!r}: cam_from_world: expected a unit quaternion, got {q.tolist()} "
                f"(norm {norm:.4g})"
            )
    pids = sorted(rec.point3D_ids()) if hasattr(rec, "point3D_ids") else sorted(rec.points3D)
    for pid in pids:
        xyz = np.asarray(rec.points3D[pid].xyz, dtype=np.float64)
        if not np.isfinite(xyz).all():
            found = [p for p in (sparse_dir / "points3D.bin", sparse_dir / "points3D.txt") if p.is_file()]
            where = found[0] if found else sparse_dir
            raise ValueError(f"{where}: point {pid}: expected finite coordinates, got {xyz.tolist()}")


def check_colmap_images(rec: pycolmap.Reconstruction, images_dir: Path, full: bool = True) -> None:
    """Every registered image of ``rec`` under ``images_dir``: present, decodable, its camera's size.

    Args:
        rec: the :class:`pycolmap.Reconstruction` (checked by :func:`check_reconstruction`).
        images_dir: the folder the names are relative to.
        full: decode each image in full (a truncated file is found); False: the headers only.

    Raises:
        FileNotFoundError: listing the missing registered images.
        ValueError: naming the image file: not decodable (truncated, 0 bytes), or of another size
            than its camera's.
    """
    from vadgs.data.checks import check_png

    missing = []
    for im in sorted(rec.images.values(), key=lambda im: im.name):
        if not im.has_pose:
            continue
        path = images_dir / check_image_name(im.name, f"{images_dir}: image {im.image_id} name")
        if not path.is_file():
            missing.append(im.name)
            continue
        cam = rec.cameras[im.camera_id]
        try:
            check_png(path, (int(cam.height), int(cam.width)), 1.0, None, full)
        except ValueError as e:
            raise ValueError(f"{path}: {e} (camera {im.camera_id}, {cam.model.name})") from None
    if missing:
        raise FileNotFoundError(
            f"images_dir {images_dir}: {len(missing)} registered image(s) missing, e.g. {missing[:3]}"
        )


# ---------------------------------------------------------------------------------------------------
# naming the file pycolmap could not read


class _Reader:
    """Sequential reads from a binary file's bytes; :class:`EOFError` past the end."""

    def __init__(self, data: bytes) -> None:
        self.data, self.pos = data, 0

    def take(self, fmt: str) -> tuple:
        size = struct.calcsize(fmt)
        if self.pos + size > len(self.data):
            raise EOFError
        out = struct.unpack_from(fmt, self.data, self.pos)
        self.pos += size
        return out

    def skip(self, nbytes: int) -> None:
        if self.pos + nbytes > len(self.data):
            raise EOFError
        self.pos += nbytes

    def cstring(self) -> bytes:
        end = self.data.find(b"\0", self.pos)
        if end < 0:
            raise EOFError
        out, self.pos = self.data[self.pos : end], end + 1
        return out


def _num_params(model_id: int) -> int | None:
    import pycolmap

    try:
        name = pycolmap.CameraModelId(model_id).name
        return len(pycolmap.Camera.create_from_model_name(1, name, 1.0, 1, 1).params)
    except (ValueError, TypeError, RuntimeError):
        return None


def _walk_binary(path: Path) -> str | None:
    """What is wrong with a COLMAP binary file's structure, or None."""
    data = path.read_bytes()
    r = _Reader(data)
    kind = path.stem
    record = -1
    try:
        (n,) = r.take("<Q")
        for record in range(n):
            if kind == "cameras":
                _, model_id, width, height = r.take("<iiQQ")
                count = _num_params(model_id)
                if count is None:
                    return f"record {record}: unknown camera model id {model_id}"
                params = r.take(f"<{count}d")
                if not all(math.isfinite(p) for p in params) or width == 0 or height == 0:
                    return f"record {record}: camera of size {width}x{height} with parameters {list(params)}"
            elif kind == "images":
                r.take("<I7dI")
                r.cstring()
                (num_points,) = r.take("<Q")
                r.skip(24 * num_points)
            else:  # points3D: id, xyz, rgb, error (43 bytes), the track's length, its (image, point2D) pairs
                if r.pos + 51 > len(data):
                    raise EOFError
                r.pos += 51 + 8 * int.from_bytes(data[r.pos + 43 : r.pos + 51], "little")
                if r.pos > len(data):
                    raise EOFError
    except EOFError:
        if record < 0:
            return f"truncated: {len(data)} bytes, too short for the record count"
        return f"truncated: the header announces {n} records, the file ends in record {record}"
    if r.pos != len(data):
        return f"{len(data) - r.pos} bytes after the last of the {n} records the header announces"
    return None


def _walk_text(path: Path) -> str | None:
    """What is wrong with a COLMAP text file's lines (the number of fields, numbers), or None."""
    lines = [
        ln for ln in path.read_text(errors="replace").splitlines() if ln.strip() and not ln.startswith("#")
    ]
    kind = path.stem
    if kind == "images":
        headers = lines[0::2]
        if len(lines) % 2:
            return f"an odd number of data lines ({len(lines)}): expected two per image"
        for ln in lines[1::2]:
            if len(ln.split()) % 3:
                return f"a POINTS2D line of {len(ln.split())} fields (expected triples): {ln[:60]!r}"
    else:
        headers = lines
    minimum = {"cameras": 5, "images": 10, "points3D": 8, "rigs": 4, "frames": 10}.get(kind, 1)
    for ln in headers:
        fields = ln.split()
        if len(fields) < minimum:
            return f"a line of {len(fields)} fields (expected at least {minimum}): {ln[:80]!r}"
        numeric = {
            "cameras": [0, *range(2, len(fields))],  # field 2 is the model's name
            "images": range(0, 9),
            "points3D": range(0, len(fields)),
            "frames": range(0, 9),
        }.get(kind, [])
        for i in numeric:
            try:
                value = float(fields[i])
            except ValueError:
                return f"field {i + 1} is not a number: {ln[:80]!r}"
            if not math.isfinite(value):
                return f"field {i + 1} is not finite: {ln[:80]!r}"
    return None


def diagnose_model_files(sparse_dir: Path) -> str | None:
    """``"FILE: what is wrong"`` for the first model file that is malformed, or None.

    Walks ``cameras``, ``images`` and ``points3D`` (``.bin`` record by record, ``.txt`` line by
    line); called when pycolmap failed to read a model, to name the file.
    """
    for stem in ("cameras", "images", "points3D", "rigs", "frames"):
        for ext in ("bin", "txt"):
            path = sparse_dir / f"{stem}.{ext}"
            if not path.is_file():
                continue
            if path.stat().st_size == 0:
                return f"{path}: an empty file (0 bytes)"
            if ext == "bin" and stem in ("rigs", "frames"):
                continue  # COLMAP 4's own layouts: left to pycolmap
            problem = _walk_binary(path) if ext == "bin" else _walk_text(path)
            if problem is not None:
                return f"{path}: {problem}"
            break
    return None


def _model_path(sparse_dir: Path, stem: str) -> Path | None:
    for ext in ("bin", "txt"):
        if (sparse_dir / f"{stem}.{ext}").is_file():
            return sparse_dir / f"{stem}.{ext}"
    return None


def _image_points(path: Path) -> dict[int, int]:
    """Image id -> its number of 2D points, from a structurally sound ``images`` file."""
    out: dict[int, int] = {}
    if path.suffix == ".bin":
        r = _Reader(path.read_bytes())
        (n,) = r.take("<Q")
        for _ in range(n):
            (iid, *_rest) = r.take("<I7dI")
            r.cstring()
            (num,) = r.take("<Q")
            r.skip(24 * num)
            out[iid] = num
        return out
    lines = [
        ln for ln in path.read_text(errors="replace").splitlines() if ln.strip() and not ln.startswith("#")
    ]
    for head, pts in zip(lines[0::2], lines[1::2]):
        out[int(head.split()[0])] = len(pts.split()) // 3
    return out


def _tracks(path: Path):
    """``(point id, (K, 2) int64 array of (image id, point2D index))`` of a sound ``points3D`` file."""
    if path.suffix == ".bin":
        data = path.read_bytes()
        (n,) = struct.unpack_from("<Q", data, 0)
        pos = 8
        for _ in range(n):
            (pid,) = struct.unpack_from("<Q", data, pos)
            (length,) = struct.unpack_from("<Q", data, pos + 43)
            pairs = np.frombuffer(data, dtype="<u4", count=2 * length, offset=pos + 51).reshape(-1, 2)
            yield pid, pairs.astype(np.int64)
            pos += 51 + 8 * length
        return
    for ln in path.read_text(errors="replace").splitlines():
        if ln.strip() and not ln.startswith("#"):
            fields = ln.split()
            yield int(fields[0]), np.asarray([int(v) for v in fields[8:]], dtype=np.int64).reshape(-1, 2)


def diagnose_references(sparse_dir: Path) -> str | None:
    """``"FILE: ..."`` for the first track that observes an image or a 2D point the model lacks, or None.

    For a model whose files are each well formed (:func:`diagnose_model_files` found nothing) but
    which pycolmap still refused (``Image with ID 9999 does not exist``).
    """
    images, points = _model_path(sparse_dir, "images"), _model_path(sparse_dir, "points3D")
    if images is None or points is None:
        return None
    known = _image_points(images)
    for pid, pairs in _tracks(points):
        for iid, idx in pairs.tolist():
            if iid not in known:
                return f"{points}: point {pid} observes image {iid}, which {images.name} does not have"
            if idx >= known[iid]:
                return (
                    f"{points}: point {pid} observes 2D point {idx} of image {iid}, which has "
                    f"{known[iid]} in {images.name}"
                )
    return None
