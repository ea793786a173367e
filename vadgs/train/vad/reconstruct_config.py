"""Settings of the reconstruction of one flagged instance by multi-view stereo.

:class:`ReconstructConfig` is the settings of :func:`~vadgs.train.vad.reconstruct.reconstruct_instance`
(view selection, crops and matching scale, PatchMatch, consistency, planar completion, fusion).
"""

from __future__ import annotations

from dataclasses import dataclass

from vadgs.checks import (
    Checked,
    bool_field,
    checked,
    choice_field,
    float_field,
    instance_field,
    int_field,
    pair_field,
)
from vadgs.mvs.patchmatch import PatchMatchConfig
from vadgs.mvs.planar import PlanarCompletionConfig
from vadgs.select.selector import ViewSelectionConfig

__all__ = ["ReconstructConfig"]

_LENGTH = float_field(0, lo_open=True)
_DOWNSAMPLE = choice_field((1, 2, 4, 8))


@dataclass(frozen=True)
class ReconstructConfig(Checked):
    """Settings of :func:`~vadgs.train.vad.reconstruct.reconstruct_instance`.

    Attributes:
        selection: view selection (``k = 4`` supporting views by default; ``method="consecutive"``
            is the paper's "w/o view selection" ablation). Its ``eps`` (metres) is read at a scene
            depth of 10 and scaled with the scene (``VisibilityIndex.scene_depth / 10``).
            Supports need a triangulation angle of ``min_angle = 1°`` with the reference
            (COLMAP's rule); ``min_parallax = 10`` (pixels of the reference) asks more of a real log
            at a low resolution, at a cost on the rendered streets (docs/results.md, "A real log").
        patchmatch: PatchMatch settings.
        margin: pixels added around each instance's bounding box for the crops.
        max_crop: crops are limited to this many pixels per side (larger instances are
            reconstructed in their central part only; keeps the cost bounded).
        max_reproj_error: forward–backward reprojection threshold (px) of the consistency check.
        max_rel_depth: relative depth threshold of the consistency check.
        min_consistent_views: other group members that must confirm a pixel.
        min_instance_voxels: below this many own voxels, the voxels seen through the instance
            in the reference view stand in for its candidates.
        min_pixels: members whose instance mask has fewer pixels are used as sources only.
        max_points: cap on the points returned (random subset, seeded).
        max_upsample: small instances, whose crop is at most ``max_crop / f`` pixels, are matched
            at ``f`` times the scene's resolution, ``f`` up to this integer and never finer than
            the image files (``1 / scene.scale``): a sign 40 px tall at half resolution gets four
            times the pixels and about half the depth error (``docs/results.md``), while the crop
            stays within ``max_crop`` so the cost stays bounded. ``1``: always the scene's resolution.
        planar: planar completion of the textureless parts of static instances
            (:func:`vadgs.mvs.complete_planar`); ``None`` turns it off. Never applied to moving
            objects: a car is not planar, and one plane fitted to it fills many of its pixels off
            its surface. On by default since small instances are matched at a finer resolution
            (``max_upsample``), where it completes thin textureless boards without tilting them
            (``docs/results.md``).
        max_match_pixels: pixel budget of one member's instance mask at the matching scale:
            an instance larger than this (a facade filling the view) is matched at 1/2, 1/4, ...
            of the scene's resolution (down to ``1 / max_downsample``), so that an event's cost
            follows the number of instances rather than their size, and its points come at the
            spacing of that scale. ``None``: always the scene's resolution (or finer).
        max_downsample: the coarsest matching scale, ``1 / max_downsample`` (1, 2, 4 or 8).
        depth_margin: ``(near, far)`` factors on the nearest and farthest instance voxel depth in
            the reference view: PatchMatch's random depths are drawn in ``[near z_min, far z_max]``.
        fallback_depth_range: the depth range when the reference sees none of the voxels; None
            (default): ``(0.5, 150)`` at a scene depth of 10, scaled with the scene
            (:func:`~vadgs.train.vad.visibility.scene_lengths`); a value: absolute.
        min_depth: lower bound of the depth range; None (default): 0.2 at a scene depth of 10,
            scaled; a value: absolute.
        explained_alpha: a consistent pixel is *explained* (gives no point) where the member's
            render has at least this opacity and a depth in front of, or within
            ``explained_tolerance`` (relative) of, the MVS depth; it still gives a depth prior.
        explained_tolerance: see ``explained_alpha``.
        max_lidar_error: the LiDAR check of an instance's reconstruction: a consistent
            pixel whose MVS depth is more than this fraction off the depth the member view's own
            sweep measured there (:meth:`VisibilityIndex.observed_depth
            <vadgs.train.vad.visibility.VisibilityIndex.observed_depth>`: the voxels of its own
            visibility set; for a moving object, those of its grid, posed at the view's time)
            gives neither a point nor a prior. A real log's small baselines and
            exposure changes let wrong matches pass the consistency check (PandaSet 002: 57.8 % of
            the static priors that met a return of their own view's sweep were more than 10 % off it,
            ``docs/results.md``). Scenes with LiDAR only: a COLMAP scene's visibility sets are SfM
            tracks, whose sparse voxels measure no pixel's depth. None: no check (the paper's).
        max_lidar_disagreement: when more than this share of the checked pixels (those with such a
            depth, at least ``min_pixels``) fail the LiDAR check, the whole reconstruction is
            dropped (reason ``"lidar_disagrees"``): its unchecked pixels come from the same wrong
            matches.
        thin_points: keep one point per cell of the point spacing (the members see the same
            surface: without it, each surface patch becomes one point per member), at the scene's
            resolution or at the coarser matching scale; the points' ``spacing`` (the new Gaussians'
            width) is that of the cell. Finer matching of small instances then gives more accurate
            points, not more of them. The cells lie on the axes of the static voxel grid's frame
            (``VisibilityIndex.ground_frame``; a moving object's own frame), not the world's.
        thin_factor: for an instance matched below the scene's resolution (a large one, such as a
            facade: ``max_match_pixels``), the cell of ``thin_points`` is this many times the
            point spacing and the new Gaussians are as much wider: fewer, larger Gaussians on
            large surfaces. Smaller instances (a sign) keep one point per pixel footprint. 1: no
            change. 1.5 by default: fewer Gaussians at the same quality (``docs/results.md``).
        whole_supports: when the instance is whole in the reference view (its mask does not touch
            the image border), select the supporting views among those where it is whole too, if
            there are ``selection.k`` of them (else among all). A view that cuts the instance off
            cannot confirm the part it does not show (e.g. the top of a sign above the frame of the
            close views the voxels favour, which stays empty).
        seen_supports: when an instance's voxels give its reference none in its visibility
            sets, or no view shares them with it (the LiDAR of a real log hits a far facade only
            from closer frames; a moving car's grid gathers the points of the frames that hit
            it), select again where the reference and the training views see the voxels in their
            voxel z-buffer as well (:meth:`VisibilityIndex.seen_covis
            <vadgs.train.vad.visibility.VisibilityIndex.seen_covis>`; a moving object's grid posed
            at each view's timestamp); the reason then ends in ``"(seen)"``. ``False``: the
            visibility sets only, as the paper's supplement.
        match_padding: the pairs of an event are matched together
            (:func:`~vadgs.train.vad.matching.match_plans`): a batched PatchMatch call pads
            every crop to the largest of the call, whose pixels are at most this many times a
            crop's (the fewer calls, the fewer kernel launches on a GPU; the more padding, the
            more pixels scored: each reference scores the union of the call's masks). 1: equal
            sizes only; None: one call (pairs of fewer source views than
            ``patchmatch.top_k`` apart).
    """

    selection: ViewSelectionConfig = checked(
        rule=instance_field(ViewSelectionConfig), default_factory=lambda: ViewSelectionConfig(min_shared=2)
    )
    patchmatch: PatchMatchConfig = checked(
        rule=instance_field(PatchMatchConfig), default_factory=lambda: PatchMatchConfig(iterations=3)
    )
    margin: int = checked(6, int_field(0))
    max_crop: int = checked(160, int_field(8, note=" pixels"))
    max_reproj_error: float = checked(2.0, float_field(0, lo_open=True))
    max_rel_depth: float = checked(0.01, float_field(0, lo_open=True))
    min_consistent_views: int = checked(1, int_field(0))
    min_instance_voxels: int = checked(8, int_field(0))
    min_pixels: int = checked(16, int_field(0))
    max_points: int = checked(20000, int_field(1))
    max_upsample: int = checked(2, int_field(1))
    planar: PlanarCompletionConfig | None = checked(
        rule=instance_field(PlanarCompletionConfig, optional=True), default_factory=PlanarCompletionConfig
    )
    max_match_pixels: int | None = checked(2048, int_field(64, optional=True))
    max_downsample: int = checked(4, lambda name, value: _DOWNSAMPLE(name, int_field()(name, value)))
    depth_margin: tuple[float, float] = checked(
        (0.5, 2.0), pair_field(_LENGTH, rule=lambda near, far: near <= 1 <= far, note="near <= 1 <= far")
    )
    fallback_depth_range: tuple[float, float] | None = checked(
        None, pair_field(_LENGTH, optional=True, rule=lambda lo, hi: lo < hi, note="lo < hi")
    )
    min_depth: float | None = checked(None, float_field(0, lo_open=True, optional=True))
    explained_alpha: float = checked(0.7, float_field(0, 1))
    explained_tolerance: float = checked(0.05, float_field(0))
    max_lidar_error: float | None = checked(0.1, float_field(0, lo_open=True, optional=True))
    max_lidar_disagreement: float = checked(0.5, float_field(0, 1))
    thin_points: bool = checked(True, bool_field())
    thin_factor: float = checked(1.5, float_field(1))
    whole_supports: bool = checked(True, bool_field())
    seen_supports: bool = checked(True, bool_field())
    match_padding: float | None = checked(4.0, float_field(1, optional=True))
