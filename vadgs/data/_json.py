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
from pathlib import Path
from typing import Any

__all__ = ["read_json", "require_key"]


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
