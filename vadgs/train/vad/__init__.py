"""VAD-GS, the paper's method: visibility-aware densification, one concept per module.

- :mod:`~vadgs.train.vad.strategy`: :class:`VisibilityAwareDensification`, the gsplat-style strategy;
- :mod:`~vadgs.train.vad.config`: its settings (:class:`VisibilityDensifyConfig`) and what the loop
  gives it (:class:`StrategyContext`);
- :mod:`~vadgs.train.vad.event`: one event: detection, ranking, references, the work budget, the
  new flat Gaussians, the priors (the strategy's ``densify`` / ``detect`` delegate to it);
- :mod:`~vadgs.train.vad.state`: the strategy's state in checkpoints (packed losslessly);
- :mod:`~vadgs.train.vad.inputs`: the data it sees (:class:`VisibilityInputs`, from a vadgs scene or
  gsplat's COLMAP parser);
- :mod:`~vadgs.train.vad.visibility`: the visibility index (voxel grids, voxel depth, covisibility);
- :mod:`~vadgs.train.vad.incomplete`: the incompleteness test;
- :mod:`~vadgs.train.vad.reconstruct` and its settings :mod:`~vadgs.train.vad.reconstruct_config`:
  an instance's reconstruction (view selection, PatchMatch, consistency, fusion);
- :mod:`~vadgs.train.vad.crops`: the crops of an instance's views that PatchMatch runs on.

The names below are the public face: ``from vadgs.train.vad import ...`` (see ``docs/vad.md``).
"""

from vadgs.train.losses import GeometryTargets
from vadgs.train.strategy.default import DefaultStrategy
from vadgs.train.vad.config import RANKINGS, StrategyContext, VisibilityDensifyConfig
from vadgs.train.vad.event import flat_gaussians, normals_to_quats, pick_references, rank_instances
from vadgs.train.vad.incomplete import IncompleteConfig, IncompleteInstances, find_incomplete
from vadgs.train.vad.inputs import TrackTable, VisibilityInputs
from vadgs.train.vad.reconstruct import InstanceReconstruction, ViewRender, reconstruct_instance
from vadgs.train.vad.reconstruct_config import ReconstructConfig
from vadgs.train.vad.state import pack_state, unpack_state
from vadgs.train.vad.strategy import VisibilityAwareDensification, check_info, info_requirements
from vadgs.train.vad.visibility import VisibilityIndex, build_visibility_index

__all__ = [
    "RANKINGS",
    "DefaultStrategy",
    "GeometryTargets",
    "IncompleteConfig",
    "IncompleteInstances",
    "InstanceReconstruction",
    "ReconstructConfig",
    "StrategyContext",
    "TrackTable",
    "ViewRender",
    "VisibilityAwareDensification",
    "VisibilityDensifyConfig",
    "VisibilityIndex",
    "VisibilityInputs",
    "build_visibility_index",
    "check_info",
    "find_incomplete",
    "flat_gaussians",
    "info_requirements",
    "normals_to_quats",
    "pack_state",
    "pick_references",
    "rank_instances",
    "reconstruct_instance",
    "unpack_state",
]
