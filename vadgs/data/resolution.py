"""The resolution a scene trains at by default (``vadgs train`` without ``--scale``): its working resolution.

On a CPU a step costs about its pixel count, so photos are trained at a working resolution, as
gsplat's ``data_factor`` and nerfstudio's automatic downscale do: the largest factor ``1 / 2^k``
(``k >= 0``) that brings the longest image side to at most :data:`WORKING_SIDE` (1024) pixels (a
1600×900 scene trains at 800×450, a 4032×3024 photo at 1008×756, a scene converted at
``--scale 0.5`` to 800×450 as it is). A rendered benchmark scene (with ground-truth depth maps,
as ``street_a`` / ``street_b`` and the bundled sample) trains at half its rendered resolution, the
resolution of its published results (:data:`BENCHMARK_SCALE`). ``--scale`` overrides both.

A scene of several image sizes (photos taken upright and sideways, cameras of a rig) trains each at
the same factor; the line that says the resolution (:meth:`WorkingResolution.describe`) names each
size at it and how many photos (COLMAP) or cameras have it: ``2 sizes: 1008x756 (20 photos),
756x1008 (3)``.
"""

from __future__ import annotations

from collections import Counter
from pathlib import Path
from typing import NamedTuple

__all__ = ["BENCHMARK_SCALE", "WORKING_SIDE", "WorkingResolution", "working_resolution", "working_scale"]

WORKING_SIDE = 1024
"""The longest image side (pixels) of the working resolution."""

BENCHMARK_SCALE = 0.5
"""The resolution factor of a rendered benchmark scene (``street_a``: 240×144 of 480×288)."""


class WorkingResolution(NamedTuple):
    """What :func:`working_resolution` chose.

    Attributes:
        scale: the resolution factor.
        size: ``(height, width)`` of the largest camera at that factor (of those with the longest
            side, the most common: photos upright rather than sideways).
        full: ``(height, width)`` of that camera as stored.
        why: the reason, for the line that says it.
        counts: ``((height, width), count)`` of each size at ``scale``, the most common first
            (count: photos of a COLMAP scene, else cameras).
        unit: what ``counts`` counts: ``"photos"`` or ``"cameras"``.
    """

    scale: float
    size: tuple[int, int]
    full: tuple[int, int]
    why: str
    counts: tuple[tuple[tuple[int, int], int], ...] = ()
    unit: str = "cameras"

    def describe(self) -> str:
        """One line: what was chosen, why, and how to change it."""
        (h, w), (fh, fw) = self.size, self.full
        change = (
            f"--scale 1 trains at full resolution ({fw}x{fh}), --scale S at S times it"
            if self.scale != 1.0
            else "--scale S (e.g. 0.5) trains at S times it"
        )
        sizes = ""
        if len(self.counts) > 1:  # photos upright and sideways, a rig of several cameras: each size
            unit = self.unit if self.counts[0][1] != 1 else self.unit[:-1]
            shown = [
                f"{sw}x{sh} ({n}{' ' + unit if i == 0 else ''})"
                for i, ((sh, sw), n) in enumerate(self.counts)
            ]
            sizes = f"; {len(self.counts)} sizes: {', '.join(shown)}"
        return f"resolution: {w}x{h} (--scale {self.scale:g} of {fw}x{fh}: {self.why}){sizes}; {change}"


def working_scale(longest: int, side: int = WORKING_SIDE) -> float:
    """The largest factor ``1 / 2^k`` (``k >= 0``) with ``longest * factor <= side``.

    Example:
        >>> working_scale(800), working_scale(1600), working_scale(4032), working_scale(1024)
        (1.0, 0.5, 0.25, 1.0)
    """
    if longest < 1 or side < 1:
        raise ValueError(f"longest, side: expected >= 1 pixel, got {longest}, {side}")
    scale = 1.0
    while longest * scale > side:
        scale /= 2
    return scale


def _sizes(path: Path, kind: str, cameras: list[str] | None) -> tuple[list[tuple[int, int]], bool]:
    """The ``(height, width)`` as stored of each camera (each posed photo's), and if rendered."""
    if kind == "benchmark":
        from vadgs.data._json import read_json

        meta = read_json((path / "scene.json") if path.is_dir() else path, "scene.json")
        cams = meta.get("cameras") or {}
        sizes = [(int(c["height"]), int(c["width"])) for c in cams.values() if isinstance(c, dict)]
        frames = meta.get("frames") or []
        rendered = any(isinstance(v, dict) and v.get("depth") for f in frames[:1] for v in f.get("views", []))
        return sizes, rendered
    if kind == "colmap":
        from vadgs.data.colmap_model import find_colmap_model, read_colmap_model

        model = find_colmap_model(path)
        if model is None:
            raise FileNotFoundError(f"{path}: no COLMAP model")
        rec = read_colmap_model(model, "SCENE")
        cams = rec.cameras
        posed = [im.camera_id for im in rec.images.values() if im.has_pose and im.camera_id in cams]
        return [(int(cams[cid].height), int(cams[cid].width)) for cid in posed], False
    if kind == "dgp":
        from vadgs.data import load_dgp

        scene = load_dgp(path, cameras=cameras, check_files=False, validate="none")
        return [c.image_size for c in scene.cameras_info.values()], False
    raise ValueError(f"kind: expected 'benchmark', 'colmap' or 'dgp', got {kind!r}")


def working_resolution(
    path: str | Path,
    kind: str,
    cameras: list[str] | None = None,
    side: int = WORKING_SIDE,
    scale: float | None = None,
) -> WorkingResolution:
    """The default resolution factor of a scene (see the module docstring), or the size at ``scale``.

    Args:
        path: the scene folder (a COLMAP model or project folder for ``kind="colmap"``).
        kind: ``"benchmark"``, ``"colmap"`` or ``"dgp"``.
        cameras: DGP: the cameras used (None: all).
        side: the working resolution's longest side.
        scale: a factor chosen by the user (``--scale``): the sizes at it, nothing chosen.

    Example:
        >>> from vadgs.data import sample_scene_path
        >>> r = working_resolution(sample_scene_path(), "benchmark")
        >>> r.scale, r.size
        (0.5, (72, 120))
        >>> working_resolution(sample_scene_path(), "benchmark", scale=0.25)[:2]
        (0.25, (36, 60))
    """
    sizes, rendered = _sizes(Path(path), kind, cameras)
    if not sizes:
        raise ValueError(f"{path}: no camera with an image size")
    stored = Counter(sizes)
    full = max(stored, key=lambda hw: (max(hw), stored[hw]))  # the largest; of those, the most common
    if scale is not None:
        why = "as given"
    elif rendered:
        scale, why = BENCHMARK_SCALE, "a rendered benchmark scene trains at half its resolution"
    else:
        scale = working_scale(max(full), side)
        why = (
            f"the working resolution, longest side <= {side} px"
            if scale < 1
            else f"longest side <= {side} px, kept as it is"
        )
    size = (round(full[0] * scale), round(full[1] * scale))
    at_scale = Counter((round(h * scale), round(w * scale)) for h, w in sizes)
    counts = tuple(sorted(at_scale.items(), key=lambda kv: (-kv[1], -max(kv[0]))))
    return WorkingResolution(scale, size, full, why, counts, "photos" if kind == "colmap" else "cameras")
