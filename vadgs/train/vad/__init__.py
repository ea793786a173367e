"""VAD-GS, the paper's method: visibility-aware densification, one concept per module.

- :mod:`~vadgs.train.vad.strategy`: :class:`VisibilityAwareDensification`, the gsplat-style strategy;
- :mod:`~vadgs.train.vad.config`: its settings (:class:`VisibilityDensifyConfig`) and what the loop
  gives it (:class:`StrategyContext`);
- :mod:`~vadgs.train.vad.event`: one event's flow (:func:`~vadgs.train.vad.event.run_event`, given an
  :class:`~vadgs.train.vad.event.EventInputs` by the strategy's ``densify``) in named steps, and
  :mod:`~vadgs.train.vad.event_log` its log and summary;
- :mod:`~vadgs.train.vad.info`: what a loop's ``info`` must carry for the base strategy, checked;
- :mod:`~vadgs.train.vad.state`: the strategy's state in checkpoints (packed losslessly);
- :mod:`~vadgs.train.vad.inputs`: the data it sees (:class:`VisibilityInputs`, from a vadgs scene or
  gsplat's COLMAP parser);
- :mod:`~vadgs.train.vad.lengths`: VAD-GS's lengths, scaled to the scene's depth;
- :mod:`~vadgs.train.vad.visibility`: the visibility index (voxel grids, voxel depth, covisibility);
- :mod:`~vadgs.train.vad.instances`: derived instance maps (ground cells, track boxes);
- :mod:`~vadgs.train.vad.incomplete`: the incompleteness test (:func:`find_incomplete`);
- :mod:`~vadgs.train.vad.detect`: an event's detection (per view, from the loop's renders);
- :mod:`~vadgs.train.vad.references`: which instances to reconstruct, from which reference views;
- :mod:`~vadgs.train.vad.survey`: an instance's voxels and frame, and what planning reads of it in
  all its pairs, once;
- :mod:`~vadgs.train.vad.reconstruct` and its settings :mod:`~vadgs.train.vad.reconstruct_config`:
  an instance's reconstruction (:func:`reconstruct_instance`: its frame, view selection, the plans,
  PatchMatch, then the steps of the next three modules);
- :mod:`~vadgs.train.vad.matching`: every (instance, reference) pair's PatchMatch, in few batched
  calls;
- :mod:`~vadgs.train.vad.crops`: the crops of an instance's views that PatchMatch runs on, at the
  instance's matching scale;
- :mod:`~vadgs.train.vad.fusion`: from the matched depth to points and priors (consistency, what
  the Gaussians already explain, fusion and thinning, each view's depth prior);
- :mod:`~vadgs.train.vad.gaussians`: the new flat Gaussians of the fused points;
- :mod:`~vadgs.train.vad.priors`: the MVS depth and normals kept as the geometric losses' targets.

The names below are the public face: ``from vadgs.train.vad import ...`` (see ``docs/vad.md``).
"""

from vadgs.train.vad.config import RANKINGS, StrategyContext, VisibilityDensifyConfig
from vadgs.train.vad.event import EventInputs, run_event
from vadgs.train.vad.gaussians import flat_gaussians
from vadgs.train.vad.incomplete import IncompleteConfig, IncompleteInstances, find_incomplete
from vadgs.train.vad.info import check_info, info_requirements
from vadgs.train.vad.inputs import TrackTable, VisibilityInputs
from vadgs.train.vad.reconstruct import InstanceReconstruction, ViewRender, reconstruct_instance
from vadgs.train.vad.reconstruct_config import ReconstructConfig
from vadgs.train.vad.references import pick_references, rank_instances
from vadgs.train.vad.state import pack_state, unpack_state
from vadgs.train.vad.strategy import VisibilityAwareDensification
from vadgs.train.vad.visibility import VisibilityIndex, build_visibility_index

__all__ = [
    "RANKINGS",
    "EventInputs",
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
    "pack_state",
    "pick_references",
    "rank_instances",
    "reconstruct_instance",
    "run_event",
    "unpack_state",
]
