"""Reading the JSON files of a dataset with one-line errors that name the file and the key.

The readers (:func:`~vadgs.data.load_scene`, :func:`~vadgs.data.load_dgp`,
:func:`~vadgs.data.load_nuscenes`) read JSON metadata written by other tools; a missing file, a
file that does not parse, a top level of the wrong kind or a missing key each raise one line that
says which file (and which key) is at fault.

Example:
    >>> import tempfile, pathlib
    >>> path = pathlib.Path(tempfile.mkdtemp()) / "calib.json"
    >>> _ = path.write_text('{"names": ["CAM"]}')
    >>> require_key(read_json(path, "calibration"), "names", "calibration")
    ['CAM']
    >>> require_key({}, "intrinsics", "calibration")
    Traceback (most recent call last):
        ...
    ValueError: calibration: missing key 'intrinsics'
"""

from __future__ import annotations

import json
import os
import warnings
from pathlib import Path, PurePosixPath
from typing import Any

__all__ = ["ALLOW_OUTSIDE_ENV", "DatasetFiles", "read_json", "require_key"]

#: Environment variable: ``1`` lets every scene read files outside its folder (as
#: ``load_scene(..., allow_outside=True)``; for the ``vadgs`` commands).
ALLOW_OUTSIDE_ENV = "VADGS_ALLOW_OUTSIDE_SCENE"


class DatasetFiles:
    """The paths a dataset's metadata names, kept inside the dataset folder unless allowed.

    Used by the readers of ``scene.json``, DGP scenes and nuScenes tables: ``files(rel, what)``
    is ``root / rel``. A path written with ``..`` or as an absolute path is refused with one line
    naming the entry (``allow_outside`` lets it through); a path that leaves the folder only
    through a symlink on disk (a data folder linked from elsewhere) is read, and :meth:`warn`
    then names those files in one :class:`UserWarning`.

    Args:
        root: the dataset folder.
        allow_outside: read files outside ``root`` without a word; None: the environment
            variable :data:`ALLOW_OUTSIDE_ENV`.
        what: the metadata's name, first in the messages.
    """

    def __init__(self, root: Path, allow_outside: bool | None = None, what: str = "scene.json") -> None:
        if allow_outside is None:
            allow_outside = os.environ.get(ALLOW_OUTSIDE_ENV, "").strip().lower() in ("1", "true", "yes")
        self.root, self.real_root, self.allow = root, root.resolve(), bool(allow_outside)
        self.linked: list[str] = []
        self.what = what

    def __call__(self, rel: str, what: str) -> Path:
        path = self.root / rel
        parts = PurePosixPath(rel.replace("\\", "/")).parts
        if not self.allow and (PurePosixPath(rel).is_absolute() or ".." in parts):
            raise ValueError(
                f"{self.what}: {what}: expected a path inside the dataset folder {self.root}, got {rel!r} "
                f"(to read files outside it: load_scene(..., allow_outside=True) or {ALLOW_OUTSIDE_ENV}=1)"
            )
        if not self.allow:
            real = path.resolve()
            if real != self.real_root and self.real_root not in real.parents:
                self.linked.append(f"{what} {rel} -> {real}")
        return path

    def warn(self) -> None:
        """One :class:`UserWarning` naming the files read through symlinks out of ``root``, if any."""
        if self.linked:
            warnings.warn(
                f"{self.what} {self.root}: {len(self.linked)} file(s) outside the folder through symlinks, "
                f"e.g. {self.linked[:2]} ({ALLOW_OUTSIDE_ENV}=1 silences this)",
                UserWarning,
                stacklevel=3,
            )


def read_json(path: Path, what: str, top: type = dict) -> Any:
    """The content of a JSON file whose top level is a ``top`` (a dict or a list).

    Args:
        path: the file.
        what: what the file is, first in every message (e.g. ``"DGP calibration"``).
        top: the expected type of the top level: ``dict`` (a JSON object) or ``list``.

    Returns:
        The parsed content.

    Raises:
        FileNotFoundError: ``"<what>: missing file <path>"``.
        ValueError: ``"<what>: <path> is not valid JSON (<reason>)"`` or
            ``"<what>: <path>: expected a JSON object at the top level"`` (``list``: a JSON list).
    """
    if not path.is_file():
        raise FileNotFoundError(f"{what}: missing file {path}")
    try:
        out = json.loads(path.read_text())
    except json.JSONDecodeError as e:
        raise ValueError(f"{what}: {path} is not valid JSON ({e})") from None
    except RecursionError:
        raise ValueError(f"{what}: {path} is nested too deeply to parse (over ~1000 levels)") from None
    if not isinstance(out, top):
        kind = "object" if top is dict else "list"
        raise ValueError(f"{what}: {path}: expected a JSON {kind} at the top level")
    return out


def require_key(d: object, key: str, what: str) -> Any:
    """``d[key]``, or a :class:`ValueError` ``"<what>: missing key '<key>'"``.

    Args:
        d: a parsed JSON object (anything else counts as lacking the key).
        key: the required key.
        what: where ``d`` is (e.g. ``"scene.json: cameras.front"``).

    Raises:
        ValueError: if ``d`` is not a dict or lacks ``key``.
    """
    if not isinstance(d, dict) or key not in d:
        raise ValueError(f"{what}: missing key {key!r}")
    return d[key]
