"""VAD-GS's lengths and how they scale with the scene (paper, Sec. 5.2).

:data:`LENGTHS` are written for a scene of depth :data:`REFERENCE_DEPTH`; :func:`scene_lengths`
scales them to another scene's depth (the visibility index, :mod:`vadgs.train.vad.visibility`,
and the reconstruction, :mod:`vadgs.train.vad.reconstruct`, read them).
"""

from __future__ import annotations

import math
from typing import Any

__all__ = [
    "LENGTHS",
    "REFERENCE_DEPTH",
    "scene_lengths",
]


#: The scene depth VAD-GS's default lengths are written for: vadgs's scenes (street metres, or SfM
#: normalised to a median view depth of 10).
REFERENCE_DEPTH = 10.0


#: VAD-GS's lengths at :data:`REFERENCE_DEPTH`; each scales with ``scene_depth / REFERENCE_DEPTH``
#: unless set explicitly (absolute): the voxel edge of the visibility grids, the ground cell of
#: derived instances, the z-buffer's near plane, PatchMatch's fallback depth range and its lower
#: bound, the smallest voxel depth and depth span of an instance (``reconstruct``), and the nearest
#: depth a track's box is painted at. (The view selection's ``ε``, ``ReconstructConfig.selection.eps``,
#: is scaled the same way: it is always read at :data:`REFERENCE_DEPTH`.)
LENGTHS: dict[str, float | tuple[float, float]] = {
    "voxel_size": 0.2,
    "cell_size": 10.0,
    "zbuffer_near": 0.1,
    "fallback_depth_range": (0.5, 150.0),
    "min_depth": 0.2,
    "min_voxel_depth": 0.1,
    "min_depth_span": 1.0,
    "box_near": 0.1,
}


def scene_lengths(scene_depth: float = REFERENCE_DEPTH, **absolute: Any) -> dict[str, Any]:
    """VAD-GS's lengths for a scene of ``scene_depth``: :data:`LENGTHS` scaled, ``absolute`` kept.

    ``None`` values of ``absolute`` mean "relative" (scaled). At :data:`REFERENCE_DEPTH` the values
    are :data:`LENGTHS` exactly.

    Example:
        >>> scene_lengths(5.0)["voxel_size"], scene_lengths(5.0, voxel_size=0.02)["voxel_size"]
        (0.1, 0.02)
        >>> scene_lengths()["cell_size"]
        10.0
    """
    unknown = set(absolute) - set(LENGTHS)
    if unknown:
        raise ValueError(f"absolute: expected keys of {sorted(LENGTHS)}, got {sorted(unknown)}")
    if not (math.isfinite(scene_depth) and scene_depth > 0):
        raise ValueError(f"scene_depth: expected a finite depth > 0, got {scene_depth}")
    unit = scene_depth / REFERENCE_DEPTH
    out = {}
    for key, value in LENGTHS.items():
        given = absolute.get(key)
        if given is not None:
            out[key] = given
        elif isinstance(value, tuple):
            out[key] = tuple(v * unit for v in value)
        else:
            out[key] = value * unit
    return out
