"""The visibility index (:mod:`vadgs.train.vad.visibility`) of the bundled sample: its memory (issue
40: it reads a segment's LiDAR frame by frame, its memory follows the voxels and a bounded sample of
points, not the number of sweeps), its bounded view cache, the voxels each view's z-buffer sees, and
which instances the image border cuts."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest
import torch

from tests.train.vad.sample import BUILDING, CAR
from vadgs.data import load_scene, sample_scene_path
from vadgs.data.lidar import accumulate_lidar
from vadgs.geometry import project_points
from vadgs.train.vad import (
    StrategyContext,
    VisibilityAwareDensification,
    build_visibility_index,
    visibility,
)


def test_sampled_ground_frame_keeps_the_grid(monkeypatch):
    """A sample of about 1 point in 64 for the ground frame: the same points in the grid, the
    frame's axes within a quarter of a degree, its origin a median of all the points."""
    scene = load_scene(sample_scene_path())
    full = build_visibility_index(scene)
    n = accumulate_lidar(scene).points.shape[0]
    assert n < visibility.GROUND_FRAME_POINTS  # the sample scene: every point, as before
    monkeypatch.setattr(visibility, "GROUND_FRAME_POINTS", n // 40)
    sampled = build_visibility_index(scene)
    assert int(sampled.grid.counts.sum()) == int(full.grid.counts.sum()) == n
    assert abs(len(sampled.grid) - len(full.grid)) < 0.05 * len(full.grid)
    r_full, r_sampled = full.static_to_world[:3, :3], sampled.static_to_world[:3, :3]
    cos = (torch.trace(r_full.T @ r_sampled) - 1) / 2
    assert float(torch.rad2deg(torch.arccos(cos.clamp(-1, 1)))) < 0.25
    # the origin is still a median of all the points along each axis (to a sample's precision)
    points = accumulate_lidar(scene).points.double()
    local = (points - sampled.static_to_world[:3, 3].double()) @ r_sampled.double()
    below = (local < 0).double().mean(0)
    assert bool(((below > 0.48) & (below < 0.52)).all()), below
    # labels: the same instances own voxels
    assert set(sampled.labels.unique().tolist()) == set(full.labels.unique().tolist())


_PEAK = r"""
import json, sys, torch
torch.set_num_threads(1)
from vadgs.process import peak_rss_mb, reset_peak_rss
from vadgs.data import load_scene
from vadgs.train.vad import visibility

visibility.GROUND_FRAME_POINTS = 50_000  # below both scenes' points: what is left grows with voxels

scene = load_scene(sys.argv[1])
assert reset_peak_rss()  # the peak from here on
before = peak_rss_mb() * 2**20
index = visibility.build_visibility_index(scene)
peak = peak_rss_mb() * 2**20 - before
print(json.dumps({"peak": peak, "voxels": len(index.grid), "tracks": len(index.track_grids)}))
"""


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc/self/status")
def test_index_peak_memory_does_not_grow_with_the_frames(tmp_path):
    """8 and 32 frames of one generated street: the peak of ``build_visibility_index`` follows its
    voxels (a longer street: 1.8x), not the LiDAR it reads (4x). The ground frame's sample
    (``GROUND_FRAME_POINTS``, a fixed bound) is set below both scenes' points, as a segment's is.
    Before, the index held every sweep with its observing views: 67 MB and 159 MB here."""
    from vadgs.data.synthetic import make_segment

    out = {}
    for frames in (8, 32):
        path = tmp_path / f"seg{frames}"
        make_segment(path, frames=frames, cameras=1, width=64, height=48, lidar_points=60_000,
                     moving_cars=1, parked_cars=0, workers=1, progress=False)  # fmt: skip
        run = subprocess.run([sys.executable, "-c", _PEAK, str(path)], capture_output=True, text=True)
        assert run.returncode == 0, run.stderr[-2000:]
        out[frames] = json.loads(run.stdout.strip().splitlines()[-1])
    assert out[32]["tracks"] == out[8]["tracks"] == 1
    per_voxel = {f: out[f]["peak"] / out[f]["voxels"] for f in out}
    assert out[32]["voxels"] > 1.5 * out[8]["voxels"]
    assert per_voxel[32] < 1.25 * per_voxel[8], out  # measured 1.07 and 1.14 kB a voxel
    assert out[32]["peak"] < 1500 * out[32]["voxels"] + 16 * 2**20, out


def test_index_cache_is_bounded_by_its_setting():
    """``cache_mb`` (``VisibilityDensifyConfig.index_cache_mb``) bounds the per-view maps; a view
    dropped from the cache is recomputed to the same values."""
    from vadgs.train.vad.inputs import VisibilityInputs

    scene = load_scene(sample_scene_path())
    inputs = VisibilityInputs.from_scene(scene)
    views = list(inputs.train_views)
    per_view = sum(x.numel() * x.element_size() for x in build_visibility_index(inputs).voxel_depth(0))
    bound_mb = 3.5 * per_view / 2**20  # room for about three views' voxel depth
    index = build_visibility_index(inputs, cache_mb=bound_mb)
    assert index.view_cache.max_bytes == int(bound_mb * 2**20)
    first = [t.clone() for t in index.voxel_depth(views[0])]
    for v in views:
        index.voxel_depth(v)
        assert index.view_cache.nbytes <= index.view_cache.max_bytes
    misses = index.view_cache.misses
    again = index.voxel_depth(views[0])  # dropped long ago: recomputed
    assert index.view_cache.misses > misses
    assert all(torch.equal(a, b) for a, b in zip(first, again))
    strategy = VisibilityAwareDensification(index_cache_mb=2.0)
    ctx = StrategyContext(render=lambda v: None, total_steps=10, steps_per_cycle=len(views))
    assert strategy.prepare(inputs, ctx).view_cache.max_bytes == 2 * 2**20
    for bad in (0, -1.0, float("nan")):
        with pytest.raises(ValueError, match="cache_mb: expected"):
            build_visibility_index(inputs, cache_mb=bad)
        with pytest.raises(ValueError, match="index_cache_mb: expected"):
            VisibilityAwareDensification(index_cache_mb=bad)


class TestViewCache:
    def test_bounded_index_gives_the_same_maps(self, scene, index):
        """A tiny byte budget drops views and recomputes them identically."""
        from vadgs.data.cache import ByteCache
        from vadgs.train.vad import build_visibility_index

        small = build_visibility_index(scene)
        small.view_cache = ByteCache(max_bytes=3 * 120 * 72 * 12)
        views = list(scene.train_views)[:8]
        for v in views + views:
            d, lab = small.voxel_depth(v)
            d0, lab0 = index.voxel_depth(v)
            assert torch.equal(d, d0) and torch.equal(lab, lab0)
            assert torch.equal(small.instances(v), index.instances(v))
        assert small.view_cache.nbytes <= small.view_cache.max_bytes
        assert len(small.view_cache.keys()) < 3 * len(views)


class TestCutByBorder:
    def test_cut_by_border_is_the_mask_touching_the_image_border(self, scene, index):
        maps = scene.load_instances(scene.train_views)
        seen = {True: 0, False: 0}
        for k, v in enumerate(scene.train_views[:12]):
            for inst in torch.unique(maps[k]).tolist():
                if inst <= 0:
                    continue
                rows, cols = torch.nonzero(maps[k] == inst, as_tuple=True)
                h, w = maps[k].shape
                expected = bool(
                    rows.min() == 0 or rows.max() == h - 1 or cols.min() == 0 or cols.max() == w - 1
                )
                assert index.cut_by_border(v, inst) == expected, (v, inst)
                seen[expected] += 1
        assert seen[True] > 5 and seen[False] > 5  # both cases occur in the sample
        assert not index.cut_by_border(scene.train_views[0], 10**6)  # absent: not cut


class TestSeenCovis:
    """``seen_covis``: an instance's visibility sets, plus the voxels the asked views' z-buffers show."""

    @staticmethod
    def _ref(scene, index):
        return max(scene.train_views, key=lambda v: int((index.instances(v) == BUILDING).sum()))

    def test_seen_covis_against_the_zbuffer(self, scene, index):
        voxels = index.labels == BUILDING
        ref = self._ref(scene, index)
        views = [ref, 3]
        cov = index.seen_covis(voxels, views)
        ids = torch.nonzero(voxels).flatten()
        for v in range(len(scene.views)):
            expect = set(index.covis.voxels_of(v).tolist())
            if v in views:
                vidx = index.voxel_raster(v)[1]
                expect |= set(vidx[vidx >= 0].tolist())
            expect = {int(i) for i in torch.nonzero(torch.isin(ids, torch.tensor(sorted(expect)))).flatten()}
            assert set(cov.voxels_of(v).tolist()) == expect, v
        assert len(cov.voxels_of(ref)) > len(index.covis.restrict(voxels).voxels_of(ref))  # the z-buffer adds


class TestSeenVoxelsOfATrack:
    """``seen_voxels`` of a moving object: the voxels of its grid a view's z-buffer shows at its timestamp."""

    def test_seen_voxels_of_a_track_are_its_front(self, scene, index):
        grid = index.track_grids[CAR]
        track = scene.tracks[CAR]
        behind = {"seen": [], "all": []}  # voxels > 3 voxel edges behind the true surface (depth maps)
        for v in scene.train_views:
            fpos = scene.frame_position(scene.views[v].frame)
            ids = index.seen_voxels(v, CAR)
            if not bool(track.valid[fpos]):
                assert len(ids) == 0
                continue
            o2w = track.object_to_world[fpos]
            cams = scene.cameras([v])
            h, w = cams.image_size
            gt = scene.load_depths([v])[0, 0]
            for name, kept in (("seen", ids), ("all", torch.arange(len(grid)))):
                world = grid.centers[kept] @ o2w[:3, :3].T + o2w[:3, 3]
                uv, z = project_points(world[None], cams.K, cams.world_to_cam)
                u, vv = uv[0, :, 0].round().long(), uv[0, :, 1].round().long()
                ok = (z[0] > 0) & (u >= 0) & (u < w) & (vv >= 0) & (vv < h)
                behind[name] += (z[0][ok] - gt[vv[ok], u[ok]] > 3 * 0.2).tolist()
        assert len(behind["seen"]) > 1000
        # the z-buffer keeps the car's visible side: almost none of its voxels behind what the view sees,
        # where its whole grid, posed there, has its far side behind it
        assert sum(behind["seen"]) / len(behind["seen"]) < 0.005
        assert sum(behind["all"]) / len(behind["all"]) > 0.03
        with pytest.raises(ValueError, match="track: expected one of the tracks"):
            index.seen_voxels(scene.train_views[0], 10**6)


class TestObservedDepth:
    """``observed_depth``: the z-buffer of the voxels the view's own sweep observed."""

    def test_observed_depth_is_the_true_surface_where_the_sweep_saw_it(self, scene, index):
        gt = scene.load_depths(scene.train_views[:10])
        covered, full = 0, 0
        for k, v in enumerate(scene.train_views[:10]):
            obs, allv = index.observed_depth(v)[0], index.voxel_raster(v)[0][0]
            assert obs.shape == allv.shape
            m = (obs > 0) & (gt[k, 0] > 0)
            rel = ((obs[m] - gt[k, 0][m]).abs() / gt[k, 0][m]).median()
            assert rel < 0.02, (v, float(rel))  # the surface the view's LiDAR hit
            covered, full = covered + int((obs > 0).sum()), full + int((allv > 0).sum())
            # where the whole scan shows nothing, the view's own voxels show nothing either
            assert not bool(((obs > 0) & (allv == 0)).any())
        assert 0.2 * full < covered < full  # the view's own sweep: a part of what the scan holds
        assert index.observed_depth(scene.train_views[0]) is index.observed_depth(scene.train_views[0])

    def test_a_tracks_observed_depth_is_its_surface_at_the_views_time(self, scene, index):
        """A moving car's grid gathers its points from every frame; posed at a view's time, the
        voxels that view's own sweep observed lie on the car's true surface, where the car is the
        nearest voxel surface, and cover less of it than the whole grid does."""
        views = [v for v in scene.train_views if int((index.instances(v) == CAR).sum()) > 50][:8]
        assert len(views) >= 4
        gt = scene.load_depths(views)
        covered, full = 0, 0
        for k, v in enumerate(views):
            obs = index.observed_depth(v, CAR)[0]
            depth, label = index.voxel_depth(v)
            m = (obs > 0) & (gt[k, 0] > 0)
            assert int(m.sum()) > 20, v
            rel = ((obs[m] - gt[k, 0][m]).abs() / gt[k, 0][m]).median()
            assert rel < 0.02, (v, float(rel))
            assert bool((label[obs > 0] == CAR).all())  # only where the car is in front
            assert torch.equal(obs[obs > 0], depth[0][obs > 0])
            covered, full = covered + int((obs > 0).sum()), full + int((label == CAR).sum())
        assert 0.1 * full < covered < full
        with pytest.raises(ValueError, match="track: expected one of the tracks"):
            index.observed_depth(views[0], 10**6)


class TestOwnVoxelDepth:
    """``own_voxel_depth``: the voxel depth where the voxel is of the pixel's own instance; with
    ``tracks=False`` the static voxels only (the default of the geometric losses' voxel prior)."""

    def test_against_the_pixels_labels(self, scene, index):
        views = [v for v in scene.train_views if int((index.instances(v) == CAR).sum()) > 50][:4]
        assert views
        tracks = set(index.track_grids)
        assert CAR in tracks and BUILDING not in tracks
        for v in views:
            depth, label = index.voxel_depth(v)
            ins = index.instances(v)
            every, static = index.own_voxel_depth(v), index.own_voxel_depth(v, tracks=False)
            own = label == ins
            moving = torch.tensor([int(t) in tracks for t in label.flatten().tolist()]).view_as(label)
            assert torch.equal(every[0], torch.where(own, depth[0], 0.0))
            assert torch.equal(static[0], torch.where(own & ~moving, depth[0], 0.0))
            assert int(((every[0] > 0) & (static[0] == 0) & (label == CAR)).sum()) > 20  # the car's
            assert int((static[0] > 0).sum()) > 100  # the static scene's kept
        assert index.own_voxel_depth(views[0], tracks=False) is index.own_voxel_depth(views[0], tracks=False)
