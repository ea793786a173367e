"""Content validation of a scene or a scene folder: :func:`validate_scene`.

:func:`validate_scene` checks a loaded :class:`~vadgs.data.Scene` (from any loader) or a
benchmark scene folder, and returns a :class:`ValidationReport`, one row per check, at one of two
levels: **headers** (the default, also run by the loaders at every load) or **full**
(``vadgs check SCENE --full``: every file decoded). The checks themselves, and what each level
reads, are in :mod:`vadgs.data.checks`; this module adds the folder (read with
:func:`~vadgs.data.load_scene` without content checks) on top of the loaders, so imports go one
way.

Example:
    >>> from vadgs.data import sample_scene_path
    >>> report = validate_scene(sample_scene_path())
    >>> report.ok, report.rows[0].item
    (True, 'cameras.front.K')
"""

from __future__ import annotations

from pathlib import Path
from typing import cast

from vadgs.data.checks import RIGID_TOLERANCE, ValidationReport, ValidationRow, check_scene
from vadgs.data.scene import Scene
from vadgs.data.scene_json import load_scene

__all__ = ["validate_scene"]


def validate_scene(
    scene: Scene | str | Path,
    full: bool = False,
    scale: float = 1.0,
    tolerance: float = RIGID_TOLERANCE,
) -> ValidationReport:
    """Check a scene's metadata and files; see :mod:`vadgs.data.checks` for what each level reads.

    Args:
        scene: a loaded :class:`~vadgs.data.Scene` (any loader), or a benchmark scene folder
            (loaded with ``validate="none"``; a ``scene.json`` that does not parse is one error row).
        full: decode every file and check its values (``vadgs check --full``).
        scale: the resolution factor when ``scene`` is a folder.
        tolerance: of the rigid-pose check (:func:`~vadgs.data.checks.check_rigid`).

    Returns:
        The :class:`ValidationReport` (never raises for a bad scene: failures are rows).
    """
    if not hasattr(scene, "views"):
        path = Path(scene)
        where = path if path.name == "scene.json" else path / "scene.json"
        try:
            scene = load_scene(path, scale=scale, check_files=False, validate="none")
        except (ValueError, FileNotFoundError, OSError) as e:
            row = ValidationRow("scene.json", str(where), "error", str(e))
            return ValidationReport(str(path), (row,), full)
    return check_scene(cast(Scene, scene), full=full, tolerance=tolerance)  # anything with views
