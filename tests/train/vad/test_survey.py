"""An instance surveyed once (:mod:`vadgs.train.vad.survey`): what planning reads of it in all its
pairs, in one host read, equal to the per-pair answers it replaces; its frame (a moving car in its
object frame, a static instance in the world)."""

from __future__ import annotations

import dataclasses

import pytest
import torch

from tests.train.vad.sample import BUILDING, CAR
from vadgs.checks import checking
from vadgs.train.vad import ReconstructConfig
from vadgs.train.vad.lengths import scene_lengths
from vadgs.train.vad.matching import MatchPlan
from vadgs.train.vad.reconstruct import plan_matches
from vadgs.train.vad.survey import instance_frame, reference_frame, survey_instance

from ...launch_count import LaunchCounter


def _views(scene, index, instance, n=4):
    """The ``n`` training views that show the instance most."""
    return sorted(scene.train_views, key=lambda v: -int((index.instances(v) == instance).sum()))[:n]


@pytest.mark.parametrize("instance", [BUILDING, CAR])
def test_one_read_and_the_per_pair_answers(scene, index, instance):
    cfg = ReconstructConfig()
    views = _views(scene, index, instance)
    with LaunchCounter() as counter:
        survey = survey_instance(index, instance, views, cfg)
    assert counter.host_reads == 1
    assert survey.track == (instance if instance == CAR else None)
    for v in views:
        assert survey.pixels[v] == int((index.instances(v) == instance).sum()) > 0
        frame = instance_frame(index, v, instance, survey.track, cfg)
        assert torch.equal(survey.frame.voxels, frame.voxels)  # its own voxels are enough here
        assert survey.allowed == frame.allowed.tolist()
        # the voxels' depths in the view against a plain computation of the voxels in front
        cen = frame.covis.voxel_centers[frame.voxels].double()
        w2c = frame.world_to_cam[v].double()
        z = cen @ w2c[2, :3] + w2c[2, 3]
        z = z[z > scene_lengths(index.scene_depth)["min_voxel_depth"]]
        n, near, far = survey.depths[v]
        assert n == len(z) > 0
        # float32 voxel centres tens of metres out: depths to a millimetre
        assert near == pytest.approx(float(z.min()), abs=1e-3)
        assert far == pytest.approx(float(z.max()), abs=1e-3)
    views_cut = sorted(set(scene.train_views) | set(views))
    assert survey.cut == {v: index.cut_by_border(v, instance) for v in views_cut}
    restricted = survey.frame.covis.restrict(survey.frame.voxels)
    assert torch.equal(survey.covis.incidence.indices(), restricted.incidence.indices())
    assert torch.equal(survey.covis.voxel_centers, restricted.voxel_centers)
    got = reference_frame(index, views[0], survey, cfg)
    assert got[0] is survey.frame and got[1] == survey.depths[views[0]]


def test_a_track_without_lidar(scene, index):
    blind = dataclasses.replace(index, track_covis={k: c for k, c in index.track_covis.items() if k != CAR})
    survey = survey_instance(blind, CAR, _views(scene, index, CAR, 2))
    assert survey.frame == "no_lidar_on_track" and survey.covis is None


def test_too_few_own_voxels_adds_those_seen_through_it(scene, index):
    """Below ``min_instance_voxels`` each reference gets its own frame (:func:`instance_frame`)."""
    views = _views(scene, index, BUILDING, 2)
    own = int((index.labels == BUILDING).sum())
    cfg = ReconstructConfig(min_instance_voxels=own + 1)
    survey = survey_instance(index, BUILDING, views, cfg)
    assert survey.covis is None and not isinstance(survey.frame, str)
    frame, (n, near, far) = reference_frame(index, views[0], survey, cfg)
    expected = instance_frame(index, views[0], BUILDING, None, cfg)
    assert torch.equal(frame.voxels, expected.voxels) and int(frame.voxels.sum()) > own
    assert n > 0 and 0 < near <= far


def test_an_instances_pairs_planned_together_as_one_by_one(scene, index):
    """One survey and one read of the plans' work for all references: the same plans as one call
    per reference (the selections draw from the generator in the references' order)."""
    cfg = ReconstructConfig(max_crop=96)
    refs = _views(scene, index, BUILDING, 2)
    g = torch.Generator().manual_seed(3)
    with LaunchCounter() as counter, checking(False):
        together = plan_matches(index, refs, BUILDING, cfg, g)
    g = torch.Generator().manual_seed(3)
    apart = [plan_matches(index, [r], BUILDING, cfg, g)[0] for r in refs]
    assert all(isinstance(p, MatchPlan) for p in together)
    for a, b in zip(together, apart):
        assert (a.ref, a.group, a.depth_range, a.selection, a.work) == (
            b.ref,
            b.group,
            b.depth_range,
            b.selection,
            b.work,
        )
        assert a.work > 0 and a.depth_range[0] < a.depth_range[1]
    # the survey, then per pair its selection (one read, two when the whole-view choice falls back)
    # and its crops, and the work of all: at most 1 + 3 per pair + 1
    assert counter.host_reads <= 2 + 3 * len(refs), counter.host_reads


class TestInstanceFrame:
    """Step 1 (``survey.instance_frame``): a moving car is matched in its object frame."""

    def test_moving_car_in_its_object_frame(self, scene, index):
        ref = max(scene.train_views, key=lambda v: int((index.instances(v) == CAR).sum()))
        frame = instance_frame(index, ref, CAR, CAR, ReconstructConfig())
        assert not isinstance(frame, str)
        covis = index.track_covis[CAR]
        assert frame.covis is covis and bool(frame.voxels.all()) and len(frame.voxels) == covis.num_voxels
        track = scene.tracks[CAR]
        cams = scene.cameras(list(range(len(scene.views))))
        checked = 0
        for v in range(len(scene.views)):
            pos = scene.frame_position(scene.views[v].frame)
            assert bool(frame.allowed[v]) == (bool(index.allowed[v]) and bool(track.valid[pos]))
            if frame.allowed[v]:  # object frame -> camera = world -> camera after the track's pose
                expected = cams.world_to_cam[v] @ track.object_to_world[pos]
                torch.testing.assert_close(frame.world_to_cam[v], expected, atol=1e-5, rtol=1e-5)
                checked += 1
        assert checked >= 5

    def test_static_instance_in_the_world(self, scene, index):
        ref = max(scene.train_views, key=lambda v: int((index.instances(v) == BUILDING).sum()))
        frame = instance_frame(index, ref, BUILDING, None, ReconstructConfig())
        assert not isinstance(frame, str)
        assert frame.covis is index.covis and torch.equal(frame.world_to_cam, index.cameras.world_to_cam)
        assert torch.equal(frame.voxels, index.labels == BUILDING)  # the facade has LiDAR voxels

    def test_a_track_without_lidar_has_nothing_to_match(self, scene, index):
        blind = dataclasses.replace(
            index, track_covis={k: c for k, c in index.track_covis.items() if k != CAR}
        )
        ref = max(scene.train_views, key=lambda v: int((index.instances(v) == CAR).sum()))
        assert instance_frame(blind, ref, CAR, CAR, ReconstructConfig()) == "no_lidar_on_track"
