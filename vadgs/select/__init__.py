"""Diversity-aware view selection: pairwise diversity scores and an exact max-weight k-clique.

For a reference view and an instance (or the whole view), choose the supporting views that give
multi-view stereo the strongest geometric constraints (paper, "Diversity-Aware View Selection";
supplement, "View Selection"). Takes tensors only (voxel centres, per-view visible voxels,
``world_to_cam``); depends on :mod:`vadgs.geometry` and nothing else of vadgs.
See ``docs/select.md``.
"""

from vadgs.select.baselines import colmap_scores, consecutive_views, mvsnet_scores, top_k_views
from vadgs.select.clique import Clique, max_weight_clique
from vadgs.select.covisibility import Covisibility, view_voxel_incidence
from vadgs.select.score import (
    DiversityScores,
    diversity_score,
    diversity_scores,
    pose_terms,
    ray_angles,
    shared_voxel_stats,
    triangulation_angles,
)
from vadgs.select.selector import METHODS, ViewSelection, ViewSelectionConfig, ViewSelector, select_views

__all__ = [
    "METHODS",
    "Clique",
    "Covisibility",
    "DiversityScores",
    "ViewSelection",
    "ViewSelectionConfig",
    "ViewSelector",
    "colmap_scores",
    "consecutive_views",
    "diversity_score",
    "diversity_scores",
    "max_weight_clique",
    "mvsnet_scores",
    "pose_terms",
    "ray_angles",
    "select_views",
    "shared_voxel_stats",
    "top_k_views",
    "triangulation_angles",
    "view_voxel_incidence",
]
