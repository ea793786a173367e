"""A writable copy of the bundled sample scene, its scene.json optionally edited (for tests that break it)."""

from __future__ import annotations

import json
import shutil
from collections.abc import Callable
from pathlib import Path

from vadgs.data import sample_scene_path


def copy_sample_scene(tmp_path: Path, edit: Callable[[dict], None] | None = None) -> Path:
    """Copy the sample scene to ``tmp_path/scene``; ``edit(meta)`` changes its scene.json in place."""
    root = tmp_path / "scene"
    shutil.copytree(sample_scene_path(), root)
    if edit is not None:
        meta = json.loads((root / "scene.json").read_text())
        edit(meta)
        (root / "scene.json").write_text(json.dumps(meta))
    return root
