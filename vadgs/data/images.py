"""The one image decoder of vadgs: any photo or image file → float RGB in ``[0, 1]``.

Every place vadgs reads a colour image (scene loaders, COLMAP projects, ``vadgs check --full``,
the VAD-GS inputs of a COLMAP run, ``vadgs sfm``) goes through :func:`read_image`, so that a file
is read the same everywhere and a file it cannot read is named with its mode.

How each PIL mode becomes RGB in ``[0, 1]`` (float32, ``(H, W, 3)``):

=====================  ==============================================================================
mode                   conversion
=====================  ==============================================================================
``1``                  0 / 1, the value in all three channels
``L``, ``P``, ``RGB``  ``/ 255`` (``L`` into all three channels; ``P`` through its palette)
``I;16`` (``B/L/N``)   ``/ 65535`` (16-bit grey PNG and TIFF), into all three channels
``I``                  ``/ 65535`` when every value is in ``[0, 65535]`` (a 16-bit file), else refused
``F``                  as is when every value is finite and in ``[0, 1]``, else refused
``CMYK``, ``YCbCr``,   PIL's conversion to RGB, ``/ 255``
``LAB``, ``HSV``
``LA``, ``PA``,        the alpha channel is **dropped** (the colour as stored, not composited): vadgs
``RGBA``, ...          trains on colour only and a photo's alpha is rarely meaningful
=====================  ==============================================================================

48- and 64-bit RGB(A) PNGs: PIL decodes them to 8 bits per sample (the high byte), so they are
read at 8-bit precision (error < 1/255), never clipped. Any other mode raises a ``ValueError``
naming the file, the mode and the modes read.

**Orientation.** :func:`read_image` returns the *stored* pixel grid and ignores an EXIF orientation
tag, as COLMAP does: the cameras of a COLMAP model are those of the stored grid. ``vadgs sfm``
turns rotated photos upright when it copies them into its project (:func:`upright_image`), and
loading a COLMAP project whose images carry a rotation warns (:func:`exif_orientation`). A tag
outside 1–8 (0, 9, ...) is taken as 1 (upright: the pixels as stored) with a warning naming the
photo, by all three (:func:`exif_orientation_tag`); PIL's warnings about a corrupt EXIF block are
re-issued naming the photo (:func:`warnings_naming`).
"""

from __future__ import annotations

import contextlib
import io
import warnings
from collections.abc import Iterator
from pathlib import Path
from typing import IO

import numpy as np
from PIL import Image, ImageOps

__all__ = [
    "SUPPORTED_MODES",
    "as_rgb",
    "decode_image",
    "exif_orientation",
    "exif_orientation_tag",
    "read_image",
    "upright_image",
    "warnings_naming",
]

#: The PIL modes :func:`read_image` reads (see the module docstring for how).
SUPPORTED_MODES = (
    "1", "L", "P", "RGB", "I;16", "I;16B", "I;16L", "I;16N", "I", "F",
    "CMYK", "YCbCr", "LAB", "HSV", "LA", "La", "PA", "RGBA", "RGBa", "RGBX",
)  # fmt: skip

_EXIF_ORIENTATION = 0x0112
_CONVERTED = ("CMYK", "YCbCr", "LAB", "HSV", "RGBX", "RGBa")
_DECODE_ERRORS = (OSError, SyntaxError, ValueError, EOFError, Image.DecompressionBombError)


def _unit8(a: np.ndarray) -> np.ndarray:
    """uint8 → float32 ``/ 255`` (one copy; the same values as ``torch``'s ``x.float() / 255``)."""
    out = a.astype(np.float32)
    out /= 255.0
    return out


def as_rgb(im: Image.Image, path: object) -> np.ndarray:
    """An opened image as float32 ``(H, W, 3)`` RGB in [0, 1], whatever its mode of :data:`SUPPORTED_MODES`.

    Raises:
        ValueError: a mode vadgs does not read, naming ``path``, the mode and the modes read.
    """
    mode = im.mode
    if mode == "P":
        im = im.convert("RGBA" if "transparency" in im.info else "RGB")
        mode = im.mode
    if mode == "PA":
        im = im.convert("RGBA")
        mode = "RGBA"
    if mode in _CONVERTED:
        arr = _unit8(np.asarray(im.convert("RGB")))
    elif mode in ("RGB", "RGBA"):
        arr = _unit8(np.asarray(im)[..., :3])
    elif mode in ("L", "LA", "La"):
        arr = _unit8(np.asarray(im.getchannel(0)))
    elif mode == "1":
        arr = np.asarray(im, dtype=np.float32)
    elif mode in ("I;16", "I;16B", "I;16L", "I;16N"):
        arr = np.asarray(im).astype(np.float32) / 65535.0
    elif mode == "I":
        raw = np.asarray(im)
        if raw.size and (raw.min() < 0 or raw.max() > 65535):
            raise ValueError(
                f"{path}: mode I (32-bit integer) with values in [{raw.min()}, {raw.max()}]; expected "
                "[0, 65535] (a 16-bit image, read / 65535)"
            )
        arr = raw.astype(np.float32) / 65535.0
    elif mode == "F":
        arr = np.asarray(im, dtype=np.float32)
        if arr.size and not (np.isfinite(arr).all() and arr.min() >= 0.0 and arr.max() <= 1.0):
            lo, hi = float(np.nanmin(arr)), float(np.nanmax(arr))
            raise ValueError(
                f"{path}: mode F (32-bit float) with values in [{lo:g}, {hi:g}] or not finite; "
                "expected finite values in [0, 1]"
            )
    else:
        raise ValueError(
            f"{path}: image mode {mode!r} is not read; expected one of {', '.join(SUPPORTED_MODES)}"
        )
    if arr.ndim == 2:
        arr = np.repeat(arr[..., None], 3, axis=-1)
    return np.ascontiguousarray(arr, dtype=np.float32)


def read_image(path: str | Path) -> np.ndarray:
    """The image at ``path`` as float32 RGB ``(H, W, 3)`` in ``[0, 1]``: its stored pixel grid.

    See the module docstring for each mode's conversion (16-bit by 65535, alpha dropped, EXIF
    orientation ignored).

    Raises:
        FileNotFoundError: if ``path`` is not a file.
        ValueError: a file that does not decode (empty, truncated, not an image) or of a mode not read,
            naming the file and the mode.

    Example:
        >>> import tempfile
        >>> p = Path(tempfile.mkdtemp()) / "grey16.png"
        >>> Image.fromarray(np.array([[0, 32768, 65535]], dtype=np.uint16)).save(p)
        >>> read_image(p)[0, :, 0].round(4).tolist()
        [0.0, 0.5, 1.0]
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"missing file {path}")
    return _decode(path, path, path.stat().st_size)


def decode_image(data: bytes, name: str) -> np.ndarray:
    """:func:`read_image` for an image held in memory (e.g. a JPEG of a Waymo parquet row).

    Args:
        data: the encoded file.
        name: what errors call it (e.g. ``"Waymo FRONT image at frame 3"``).

    Example:
        >>> import io
        >>> buf = io.BytesIO()
        >>> Image.new("L", (2, 1), 255).save(buf, format="PNG")
        >>> decode_image(buf.getvalue(), "x").shape
        (1, 2, 3)
    """
    return _decode(io.BytesIO(data), name, len(data))


def _decode(source: Path | IO[bytes], name: object, nbytes: int) -> np.ndarray:
    try:
        with warnings_naming(name), Image.open(source) as im:
            im.load()
            return as_rgb(im, name)
    except ValueError as e:
        if str(e).startswith(str(name)):
            raise
        raise _undecodable(name, nbytes, e) from None
    except _DECODE_ERRORS as e:
        raise _undecodable(name, nbytes, e) from None


def _undecodable(name: object, nbytes: int, e: BaseException) -> ValueError:
    what = "an empty file (0 bytes)" if nbytes == 0 else f"{type(e).__name__}: {e}"
    return ValueError(f"{name}: not a decodable image ({what})")


@contextlib.contextmanager
def warnings_naming(name: object) -> Iterator[None]:
    """Re-issue the warnings raised inside the block with ``name`` first (PIL's name no file).

    PIL warns ``Corrupt EXIF data.  Expecting to read 12 bytes but only got 10.`` for a photo whose
    EXIF block is damaged; inside this block the warning reads ``<name>: Corrupt EXIF data. ...``.

    Example:
        >>> with warnings.catch_warnings(record=True) as w:
        ...     warnings.simplefilter("always")
        ...     with warnings_naming("a.jpg"):
        ...         warnings.warn("Corrupt EXIF data.")
        >>> str(w[0].message)
        'a.jpg: Corrupt EXIF data.'
    """
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        yield
    for w in caught:
        text = str(w.message).strip()
        warnings.warn(text if text.startswith(f"{name}: ") else f"{name}: {text}", w.category, stacklevel=3)


def exif_orientation_tag(exif: Image.Exif, name: object) -> int:
    """The orientation tag of an EXIF block: 1–8 (1 when absent); any other value is taken as 1.

    A value outside 1–8 (0, 9, text) names no rotation: it is taken as upright (the pixels as
    stored) and a warning naming ``name`` says so.

    Example:
        >>> exif = Image.Exif()
        >>> exif[0x0112] = 9
        >>> with warnings.catch_warnings(record=True) as w:
        ...     warnings.simplefilter("always")
        ...     exif_orientation_tag(exif, "a.jpg")
        1
        >>> str(w[0].message)
        'a.jpg: EXIF orientation 9 is not one of 1-8: taken as 1 (upright, the pixels as stored)'
    """
    raw = exif.get(_EXIF_ORIENTATION, 1)
    try:
        value = int(raw) if raw is not None else 1
    except (TypeError, ValueError):
        value = 0
    if 1 <= value <= 8:
        return value
    warnings.warn(
        f"{name}: EXIF orientation {raw!r} is not one of 1-8: taken as 1 (upright, the pixels as stored)",
        UserWarning,
        stacklevel=2,
    )
    return 1


def exif_orientation(path: str | Path) -> int:
    """The EXIF orientation tag of an image file (1–8; 1, as stored, when absent or unreadable).

    Example:
        >>> import tempfile
        >>> p = Path(tempfile.mkdtemp()) / "a.jpg"
        >>> exif = Image.Exif()
        >>> exif[0x0112] = 6
        >>> Image.new("RGB", (4, 2)).save(p, exif=exif)
        >>> exif_orientation(p)
        6
    """
    try:
        with warnings_naming(path), Image.open(path) as im:
            return exif_orientation_tag(im.getexif(), path)
    except (*_DECODE_ERRORS, TypeError):
        return 1


def upright_image(src: str | Path, dst: str | Path) -> int:
    """Write ``src`` turned upright by its EXIF orientation to ``dst``; its orientation tag.

    The pixels are transposed (:func:`PIL.ImageOps.exif_transpose`) and the tag removed, so that
    COLMAP and vadgs, which read the stored grid, see what a viewer shows. The other EXIF fields
    (camera, focal length) are kept. JPEGs are re-encoded at quality 95 with the source's chroma
    subsampling kept where PIL knows it (``keep`` is not possible after a transpose); other formats
    (PNG, TIFF, BMP) are lossless. A photo without a rotation (tag 1) is not written: the caller
    copies it byte for byte.

    Example:
        >>> import tempfile
        >>> d = Path(tempfile.mkdtemp())
        >>> exif = Image.Exif()
        >>> exif[0x0112] = 6
        >>> Image.new("RGB", (4, 2)).save(d / "a.png", exif=exif)
        >>> upright_image(d / "a.png", d / "b.png"), Image.open(d / "b.png").size
        (6, (2, 4))
    """
    src, dst = Path(src), Path(dst)
    with warnings_naming(src), Image.open(src) as im:
        orientation = exif_orientation_tag(im.getexif(), src)
        if orientation == 1:
            return 1
        fmt = im.format
        icc = im.info.get("icc_profile")
        out = ImageOps.exif_transpose(im)
        exif = out.getexif()
        exif.pop(_EXIF_ORIENTATION, None)
        kw: dict = {"exif": exif.tobytes()}
        if icc:
            kw["icc_profile"] = icc
        if fmt in ("JPEG", "MPO"):  # MPO: a phone's JPEG with extra pictures (depth); the first kept
            fmt = "JPEG"
            kw.update(quality=95, subsampling=_subsampling(im))
        out.save(dst, format=fmt, **kw)
    return orientation


def _subsampling(im: Image.Image) -> int:
    try:
        from PIL import JpegImagePlugin

        value = JpegImagePlugin.get_sampling(im)
    except Exception:
        return 2
    return value if value in (0, 1, 2) else 2
