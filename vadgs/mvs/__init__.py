"""Batched PatchMatch multi-view stereo, consistency checks and fusion.

See ``docs/mvs.md`` for a worked example and ``vadgs/mvs/design.md`` for the design.
"""

from vadgs.mvs.consistency import ConsistencyResult, geometric_consistency, reproject_depth
from vadgs.mvs.cost import (
    MAX_COST,
    ReferencePatchStats,
    bilateral_ncc,
    bilateral_weights,
    ncc_cost_from_stats,
    patch_offsets,
    reference_patch_stats,
    reference_patches,
)
from vadgs.mvs.fill import fill_holes_scanline
from vadgs.mvs.fusion import FusedPoints, FusionConfig, fuse_depth_maps
from vadgs.mvs.patchmatch import (
    PatchMatch,
    PatchMatchConfig,
    PatchMatchResult,
    patchmatch,
    propagation_regions,
)
from vadgs.mvs.planar import (
    PlanarCompletionConfig,
    PlaneFit,
    complete_planar,
    fit_plane_ransac,
)

__all__ = [
    "MAX_COST",
    "ConsistencyResult",
    "FusedPoints",
    "FusionConfig",
    "PatchMatch",
    "PatchMatchConfig",
    "PatchMatchResult",
    "PlanarCompletionConfig",
    "PlaneFit",
    "ReferencePatchStats",
    "bilateral_ncc",
    "bilateral_weights",
    "complete_planar",
    "fill_holes_scanline",
    "fit_plane_ransac",
    "fuse_depth_maps",
    "geometric_consistency",
    "ncc_cost_from_stats",
    "patch_offsets",
    "patchmatch",
    "propagation_regions",
    "reference_patch_stats",
    "reference_patches",
    "reproject_depth",
]
