"""Settings of the VAD-GS strategy and the context it is given by the training loop.

:class:`VisibilityDensifyConfig` holds the settings of
:class:`~vadgs.train.vad.VisibilityAwareDensification` (the strategy holds one in ``config``, its
fields readable and assignable as the strategy's attributes); :class:`StrategyContext` is what
the strategy needs of the loop (a render function, step counts, a generator). Both are importable from
:mod:`vadgs.train.vad`.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, replace

import torch

from vadgs.checks import (
    Checked,
    bool_field,
    checked,
    choice_field,
    float_field,
    instance_field,
    int_field,
    names_field,
    nested,
)
from vadgs.train.vad.incomplete import IncompleteConfig
from vadgs.train.vad.reconstruct import ViewRender
from vadgs.train.vad.reconstruct_config import ReconstructConfig

__all__ = ["RANKINGS", "StrategyContext", "VisibilityDensifyConfig"]

RANKINGS = ("class_round_robin", "pixels")


@dataclass(frozen=True)
class VisibilityDensifyConfig(Checked):
    """Settings of :class:`~vadgs.train.vad.VisibilityAwareDensification` (paper values by default).

    VAD-GS is on wherever this config is given (``TrainConfig.vad``); the paper's "w/o voxel
    visibility reasoning" ablation, which disables everything else, is its absence
    (``TrainConfig.vad = None``, ``vadgs train`` without ``--vad``: the standard strategy alone).

    Attributes:
        view_selection: diversity-aware selection (False: consecutive frames of the reference
            camera, the "w/o view selection" ablation).
        geometric_losses: normal and hard/soft depth losses on the priors.
        every_cycles: detection and densification every this many complete sampling cycles.
        scene_depth: the scene's length unit, its typical view depth: every length left unset
            below (``voxel_size``, ``cell_size``, ``reconstruct.fallback_depth_range`` /
            ``min_depth``, and the internal ones of :data:`~vadgs.train.vad.lengths.LENGTHS`) is its
            value for a scene of depth 10 times ``scene_depth / 10``, so that VAD-GS does the same
            on a scene at any scale. None (default): the inputs'
            (:meth:`~vadgs.train.vad.inputs.VisibilityInputs.median_view_depth`: 10 for vadgs's
            scenes; for gsplat's Parser, the median depth of its SfM observations in its
            normalised world). Not gsplat's ``scene_scale`` (the cameras' spread, which is not a
            depth: a street drive spreads its cameras far beyond what they see).
        voxel_size: voxel edge of the visibility grids; None (default): 0.2 at a scene depth of 10
            (0.02 ``scene_depth``); a value: absolute (world units).
        cell_size: ground-cell edge of the derived instances of scenes without instance maps
            (COLMAP, gsplat's Parser): None (default): 10 at a scene depth of 10 (one
            ``scene_depth``); a value: absolute.
        incomplete: thresholds of the incompleteness test.
        reconstruct: view selection / PatchMatch / consistency settings.
        max_instances: at most this many instances reconstructed per event, in the order of
            ``ranking`` (``None``, the default: every flagged instance, within ``work_budget``).
        work_budget: an event stops starting new instances once its PatchMatch has done this
            many pixel-sweeps (:func:`~vadgs.train.vad.matching.match_work`: reference pixels ×
            source views × sweeps) per training pixel so far (the steps so far × the training
            views' mean pixel count); the instances left are logged as skipped
            (``"work_budget"``) and tried at the next event. The first instance is always tried.
            A count of work, not of seconds: one config and seed give one model on any machine,
            under any load, and on exact resume. 0.1 by default: enough for every candidate
            instance of a first event on the benchmark streets (``docs/vad.md``). ``None``: no
            limit.
        time_budget: opt-in wall-clock safety cap (off by default): an event also stops starting
            instances once it has taken this fraction of the training time so far (the time
            between the strategy's calls, events excluded), logged as skipped (``"time_budget"``)
            with a note in the event's summary. A run it cuts depends on the machine's speed and
            load. ``None`` (default): no cap.
        index_cache_mb: the bound of the visibility index's per-view maps (voxel z-buffer and
            depth, instance map, image; :class:`~vadgs.data.cache.ByteCache`), in MiB;
            views dropped are recomputed identically when an event needs them again. 1024 by
            default (every view of the benchmark streets; about a hundred at 1920×1280: lower it
            to bound an event's memory on a long segment, ``docs/scale.md``).
        render_cache_mb: the loop's renders of the views trained since the last event (depth
            float16, opacity uint8, normals as two int8 octahedral codes: 5 bytes a pixel, see
            :func:`~vadgs.train.vad.state.compact_render`; in the strategy's state, so checkpoints
            hold them and a resumed run stays exact) are kept up to this size and reused by the
            event for detection, PatchMatch initialisation and the test of what is already
            explained (the event tests them for incompleteness together, a render dropped for
            room is tested when dropped); the views beyond it are rendered at the event when it
            needs their render. ``0``: each step tests its own render, the event renders the
            views it reconstructs from.
        references: reference views per instance: its flagged view with the most pixels, then
            the next largest ones from another camera or at least ``min_frame_gap`` frames away
            from those already chosen (another side of the object, e.g. the back of a sign).
            3 by default (the measured trade of a third reference: ``docs/results.md``).
        min_frame_gap: see ``references``.
        ranking: ``"class_round_robin"`` (default): one instance per class in turn, the largest
            (most pixels in its best flagged view) first within a class, so that small structures
            such as signs are not starved by large facades; ``"pixels"``: largest first overall.
        cooldown_events: an instance reconstructed at an event is skipped for this many events
            (default 0: an instance still flagged at the next event is tried again; what the
            Gaussians already explain gives no new points, so a repeat adds only what is missing).
        whole_reference: at least one reference in which the instance is whole when it was
            flagged in such a view (``whole`` of :func:`~vadgs.train.vad.event.pick_references`); with
            ``reconstruct.whole_supports`` its supporting views show all of it too.
        skip_classes: instance classes never densified (e.g. the road, which LiDAR covers).
        new_opacity: opacity of the new Gaussians.
        flatness: thickness of the new Gaussians along their normal, relative to their width.
        voxel_depth_prior: use the voxel depth where no MVS depth exists.
        voxel_prior_tracks: the voxel depth prior on moving objects' pixels too (their grid,
            gathered from every frame through that frame's box, posed at the view's time). False
            by default, a documented deviation: a real log's boxes jitter by centimetres to
            decimetres, so the gathered grid lies in front of the car's own return (PandaSet 002:
            19 % of the tracks' prior more than 10 % off the view's sweep), and the dense prior on
            the cars cost PSNR* (frames 36–55, two seeds, ``docs/results.md``); the trainer's LiDAR
            loss on the view's own sweep still measures them.
        mvs_prior_beyond_voxels: keep the MVS depth and normal priors only where the view's voxel
            z-buffer is empty (beyond the LiDAR's reach: the paper's sign above it, a facade out of
            range); where a voxel surface is on the ray, the trainer's LiDAR loss measures it, and
            on the static voxels the voxel depth (``voxel_depth_prior``). Cut once, when an event
            keeps its priors. Scenes with LiDAR only: a COLMAP scene's voxels
            are its sparse SfM points, which leave most rays unmeasured. True by default, a
            documented deviation (False: everywhere, as the paper): on a real log the MVS depth at
            the LiDAR's edges is often off (PandaSet 002: 30 % of the priors on a return of the
            view's own sweep more than 10 % off it), and the losses on it cost PSNR* and depth
            (frames 36–55, two seeds: PSNR* −0.6 to −0.8 dB, AbsRel 0.056–0.059 against the
            baseline's 0.047–0.048; beyond the voxels only: level); the rendered streets keep their
            figures (``docs/results.md``, round 33).
        last_event_fraction: no event after this fraction of the iterations (Gaussians added at
            the very end would not be trained).
    """

    view_selection: bool = checked(True, bool_field())
    geometric_losses: bool = checked(True, bool_field())
    every_cycles: int = checked(5, int_field(1))
    scene_depth: float | None = checked(None, float_field(0, lo_open=True, optional=True))
    voxel_size: float | None = checked(None, float_field(0, lo_open=True, optional=True))
    cell_size: float | None = checked(None, float_field(0, lo_open=True, optional=True))
    incomplete: IncompleteConfig = nested(IncompleteConfig)
    reconstruct: ReconstructConfig = nested(ReconstructConfig)
    max_instances: int | None = checked(None, int_field(0, optional=True))
    work_budget: float | None = checked(0.1, float_field(0, lo_open=True, optional=True))
    time_budget: float | None = checked(None, float_field(0, lo_open=True, optional=True))
    index_cache_mb: float = checked(1024.0, float_field(0, lo_open=True))
    render_cache_mb: float = checked(256.0, float_field(0))
    references: int = checked(3, int_field(1))
    min_frame_gap: int = checked(3, int_field(0))
    ranking: str = checked("class_round_robin", choice_field(RANKINGS))
    cooldown_events: int = checked(0, int_field(0))
    whole_reference: bool = checked(True, bool_field())
    skip_classes: tuple[str, ...] = checked(("road",), names_field("class names"))
    new_opacity: float = checked(0.5, float_field(0, 1, lo_open=True, hi_open=True))
    flatness: float = checked(0.2, float_field(0, lo_open=True))
    voxel_depth_prior: bool = checked(True, bool_field())
    voxel_prior_tracks: bool = checked(False, bool_field())
    mvs_prior_beyond_voxels: bool = checked(True, bool_field())
    last_event_fraction: float = checked(0.9, float_field(0, 1))

    def effective_reconstruct(self) -> ReconstructConfig:
        """``reconstruct`` as the event runs it: consecutive-frame selection when ``view_selection`` is off.

        Example:
            >>> VisibilityDensifyConfig(view_selection=False).effective_reconstruct().selection.method
            'consecutive'
        """
        if self.view_selection:
            return self.reconstruct
        selection = replace(self.reconstruct.selection, method="consecutive")
        return replace(self.reconstruct, selection=selection)


def _render_rule(name: str, value: object) -> object:
    if not callable(value):
        raise ValueError(f"{name}: expected a function view -> ViewRender, got {type(value).__name__}")
    return value


@dataclass(frozen=True)
class StrategyContext(Checked):
    """What the VAD-GS strategy (:class:`~vadgs.train.vad.VisibilityAwareDensification`) needs of the loop.

    Attributes:
        render: ``view -> ViewRender``: renders a view (index into the inputs' views, e.g.
            ``scene.views`` or the Parser's images) with the current Gaussians, at the view's frame,
            without gradient; normals may be zeros (unknown).
        total_steps: the run's number of steps (events stop after ``last_event_fraction`` of it).
        steps_per_cycle: steps of one sampling cycle (vadgs's trainer: one view per step, so the
            number of training views); cycle ``c`` ends after step ``c * steps_per_cycle - 1``.
        generator: seeds the view-selection noise ``ξ`` and point subsampling (checkpoint it for
            exact resume; vadgs's trainer passes its own).
        track_nodes: track id → node index of ``params["node_ids"]`` (default: the inputs' tracks
            in sorted order, as :func:`~vadgs.train.init.init_gaussians` numbers them). Without
            ``node_ids`` in ``params`` (a static gsplat model) moving objects are not densified.

    Example:
        >>> ctx = StrategyContext(render=lambda v: None, total_steps=3000, steps_per_cycle=40)
        >>> ctx.steps_per_cycle
        40
    """

    render: Callable[[int], ViewRender] = checked(rule=_render_rule)
    total_steps: int = checked(rule=int_field(0))
    steps_per_cycle: int = checked(rule=int_field(1))
    generator: torch.Generator | None = checked(None, instance_field(torch.Generator, optional=True))
    track_nodes: Mapping[int, int] | None = checked(None, instance_field(Mapping, optional=True))
