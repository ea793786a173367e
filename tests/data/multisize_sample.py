"""A rig with two image sizes: the bundled sample with one camera's images cropped (for tests).

The crop keeps the top-left ``(height, width)`` of every image, depth and instance map of the
camera, so its intrinsics stay as they are (pixel coordinates do not move).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from PIL import Image

from tests.data.sample_copy import copy_sample_scene


def write_multisize_sample(
    tmp_path: Path, camera: str = "front_left", size: tuple[int, int] = (120, 200)
) -> Path:
    """Copy the sample scene to ``tmp_path/scene`` with ``camera`` cropped to ``size`` ``(H, W)``."""
    h, w = size
    root = copy_sample_scene(tmp_path)
    meta = json.loads((root / "scene.json").read_text())
    meta["cameras"][camera]["width"], meta["cameras"][camera]["height"] = w, h
    for frame in meta["frames"]:
        for view in frame["views"]:
            if view["camera"] != camera:
                continue
            for key in ("image", "instances"):
                if view.get(key):
                    path = root / view[key]
                    Image.fromarray(np.asarray(Image.open(path))[:h, :w]).save(path)
            if view.get("depth"):
                path = root / view["depth"]
                depth = np.load(path)["depth"][:h, :w]
                np.savez_compressed(path, depth=depth)
    (root / "scene.json").write_text(json.dumps(meta))
    return root
