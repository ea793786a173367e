"""The folder of photos that ``vadgs sfm`` reads: which files are photos, and which share a camera.

:func:`find_photos` lists the photos of a folder (:data:`PHOTO_SUFFIXES`: what both COLMAP and PIL
read; hidden files and other kinds skipped) and :func:`unsupported_photos` the photos of formats
it leaves out (:data:`OTHER_PHOTO_SUFFIXES`, named in one line by :func:`left_out_line`).
:func:`read_photo_header` reads a photo's size, EXIF camera and orientation without decoding it;
:func:`photo_groups` / :func:`group_photos` put the photos that share a camera together
(:data:`CAMERA_MODES`: ``"auto"``, one camera per pixel size and EXIF camera — make, model, focal
length —; ``"single"``, one for all; ``"per-image"``, one each). :func:`distinct_photos` decodes
every photo (a corrupt one named) and finds those with identical pixels.
:func:`vadgs.data.sfm.run_sfm` uses them all.
"""

from __future__ import annotations

import hashlib
from collections.abc import Sequence
from pathlib import Path
from typing import NamedTuple

from PIL import Image

from vadgs.data.images import exif_orientation_tag, read_image, warnings_naming

__all__ = [
    "CAMERA_MODES",
    "OTHER_PHOTO_SUFFIXES",
    "PHOTO_SUFFIXES",
    "PhotoHeader",
    "distinct_photos",
    "find_photos",
    "group_photos",
    "left_out_line",
    "photo_groups",
    "read_photo_header",
    "unsupported_photos",
]

#: The photo files :func:`find_photos` takes (case-insensitive): what both COLMAP and PIL read.
PHOTO_SUFFIXES = (".jpg", ".jpeg", ".png", ".tif", ".tiff", ".bmp")
#: Photo files :func:`find_photos` leaves out (COLMAP's image reader does not take them) and
#: :func:`vadgs.data.sfm.run_sfm` names in one line, with :func:`unsupported_photos`.
OTHER_PHOTO_SUFFIXES = (
    ".webp", ".avif", ".heic", ".heif", ".gif", ".jxl", ".jp2",
    ".dng", ".cr2", ".cr3", ".nef", ".arw", ".raw",
)  # fmt: skip

#: The ways to make cameras (see :func:`photo_groups`).
CAMERA_MODES = ("auto", "single", "per-image")

_EXIF_CAMERA = (0x010F, 0x0110)  # Make, Model (IFD0)
_EXIF_FOCAL = 0x920A  # FocalLength (Exif IFD)


def find_photos(folder: str | Path) -> list[str]:
    """The photos in ``folder`` and its subfolders: names relative to it (``/``-separated), sorted.

    Files of other kinds (``.txt``, ``.mov``, ...) and hidden files are skipped.

    Raises:
        FileNotFoundError: if ``folder`` does not exist.
        ValueError: if it is a file, or holds no photo (naming the suffixes taken and what else it holds).
    """
    folder = Path(folder)
    if folder.exists() and not folder.is_dir():
        raise ValueError(f"PHOTOS {folder}: expected a folder of photos, got a file")
    if not folder.is_dir():
        raise FileNotFoundError(f"PHOTOS {folder}: no such folder")
    names, other = [], 0
    for rel in _visible_files(folder):
        if rel.suffix.lower() in PHOTO_SUFFIXES:
            names.append(rel.as_posix())
        else:
            other += 1
    if not names:
        left = unsupported_photos(folder)
        also = f"; {left_out_line(left)}" if left else ""
        raise ValueError(
            f"PHOTOS {folder}: expected photos ({', '.join(PHOTO_SUFFIXES)}), got none "
            f"({other} other file(s)){also}"
        )
    return names


def _visible_files(folder: Path) -> list[Path]:
    """The files under ``folder`` (relative), hidden ones and those in hidden folders left out."""
    out = []
    for path in sorted(folder.rglob("*")):
        rel = path.relative_to(folder)
        if not any(part.startswith(".") for part in rel.parts) and path.is_file():
            out.append(rel)
    return out


def unsupported_photos(folder: str | Path) -> list[str]:
    """The photos in ``folder`` that :func:`find_photos` leaves out (:data:`OTHER_PHOTO_SUFFIXES`).

    Example:
        >>> import tempfile
        >>> d = Path(tempfile.mkdtemp())
        >>> for name in ("a.jpg", "b.webp", "c.HEIC", "notes.txt"):
        ...     _ = (d / name).write_bytes(b"")
        >>> unsupported_photos(d)
        ['b.webp', 'c.HEIC']
    """
    folder = Path(folder)
    if not folder.is_dir():
        return []
    return [r.as_posix() for r in _visible_files(folder) if r.suffix.lower() in OTHER_PHOTO_SUFFIXES]


def left_out_line(names: Sequence[str]) -> str:
    """One line naming the photos of formats that vadgs sfm does not take (:func:`unsupported_photos`)."""
    kinds = sorted({Path(n).suffix.lower() for n in names})
    shown = ", ".join(names[:5]) + (f", ... ({len(names) - 5} more)" if len(names) > 5 else "")
    return (
        f"left out {len(names)} photo(s) in formats vadgs sfm does not take ({', '.join(kinds)}): {shown}; "
        "convert them to JPEG or PNG to use them"
    )


class PhotoHeader(NamedTuple):
    """What :func:`read_photo_header` reads of a photo without decoding its pixels.

    Attributes:
        size: the stored pixel grid ``(W, H)``.
        camera: EXIF make, model, focal length (empty strings when absent).
        orientation: EXIF orientation tag (1: as stored).
    """

    size: tuple[int, int]
    camera: tuple
    orientation: int

    @property
    def label(self) -> str:
        """``WxH make model`` (``WxH`` without an EXIF camera): how ``vadgs sfm`` names a camera group."""
        make, model, _ = self.camera
        label = f"{self.size[0]}x{self.size[1]}"
        return f"{label} {make} {model}".strip() if (make or model) else label


def read_photo_header(path: Path) -> PhotoHeader:
    """A photo's :class:`PhotoHeader` (its EXIF and size; the pixels are not decoded).

    Raises:
        ValueError: naming the photo, when PIL cannot read it.
    """
    try:
        with warnings_naming(path), Image.open(path) as im:
            exif = im.getexif()
            focal = exif.get_ifd(0x8769).get(_EXIF_FOCAL, "")
            camera = (*(str(exif.get(tag, "")).strip() for tag in _EXIF_CAMERA), str(focal))
            return PhotoHeader(im.size, camera, exif_orientation_tag(exif, path))
    except (OSError, SyntaxError, ValueError, Image.DecompressionBombError) as e:
        raise ValueError(f"PHOTOS: {path} is not a readable photo ({type(e).__name__}: {e})") from None


def photo_groups(folder: str | Path, names: Sequence[str], camera_mode: str = "auto") -> list[list[str]]:
    """The photos that share a camera: ``names`` in groups (see the module docstring, ``camera_mode``).

    Raises:
        ValueError: for an unknown ``camera_mode``, an unreadable photo, or ``"single"`` with photos
            of several sizes.

    Example:
        >>> import tempfile
        >>> from PIL import Image
        >>> d = Path(tempfile.mkdtemp())
        >>> for name, size in (("a.png", (40, 30)), ("b.png", (40, 30)), ("c.png", (30, 40))):
        ...     Image.new("RGB", size).save(d / name)
        >>> photo_groups(d, ["a.png", "b.png", "c.png"])
        [['a.png', 'b.png'], ['c.png']]
    """
    if camera_mode not in CAMERA_MODES:
        raise ValueError(f"camera_mode: expected one of {list(CAMERA_MODES)}, got {camera_mode!r}")
    return group_photos({name: read_photo_header(Path(folder) / name) for name in names}, camera_mode)


def group_photos(headers: dict[str, PhotoHeader], camera_mode: str) -> list[list[str]]:
    """The names of ``headers`` in groups that share a camera (see :func:`photo_groups`).

    Raises:
        ValueError: ``"single"`` with photos of several sizes.
    """
    names = list(headers)
    if camera_mode == "per-image":
        return [[name] for name in names]
    if camera_mode == "single":
        sizes = sorted({h.size for h in headers.values()})
        if len(sizes) > 1:
            shown = ", ".join(f"{w}x{h}" for w, h in sizes[:4])
            raise ValueError(
                f"camera_mode: 'single' needs photos of one size, got {len(sizes)} sizes ({shown}); "
                "use 'auto' (one camera per size)"
            )
        return [list(names)]
    groups: dict[tuple, list[str]] = {}
    for name in names:
        groups.setdefault((headers[name].size, headers[name].camera), []).append(name)
    return list(groups.values())


def distinct_photos(photos: Path, names: Sequence[str]) -> tuple[list[str], dict[str, str]]:
    """Every photo decoded (a corrupt one named); ``(names kept, {duplicate: the photo it repeats})``.

    Identical photos have no baseline between them (COLMAP cannot place them): all but the first
    are left out.

    Raises:
        ValueError: naming a photo that cannot be decoded.
    """
    seen: dict[str, str] = {}
    kept, duplicates = [], {}
    for name in names:
        try:
            pixels = read_image(photos / name)
        except ValueError as e:
            raise ValueError(f"PHOTOS: {e}; remove or replace that photo") from None
        key = hashlib.sha1(repr(pixels.shape).encode() + pixels.tobytes()).hexdigest()
        if key in seen:
            duplicates[name] = seen[key]
        else:
            seen[key] = name
            kept.append(name)
    return kept, duplicates
