"""VAD-GS strategy on the bundled sample: complete geometry is not flagged, deleted geometry is
flagged and re-populated on the true surface, moving-object Gaussians live in the object frame."""

import pytest
import torch

from vadgs.data import load_scene, sample_scene_path
from vadgs.geometry import backproject_depth, project_points
from vadgs.geometry.rotation import normals_to_quats
from vadgs.mvs import PlanarCompletionConfig
from vadgs.train.config import TrainConfig
from vadgs.train.model import GaussianModel
from vadgs.train.trainer import Trainer
from vadgs.train.vad import (
    ReconstructConfig,
    StrategyContext,
    VisibilityAwareDensification,
    VisibilityDensifyConfig,
    build_visibility_index,
    pick_references,
    rank_instances,
)
from vadgs.train.vad.event import EventInputs, add_reconstructions
from vadgs.train.vad.reconstruct import reconstruct_instance

BUILDING = 9  # a large facade of the sample scene with LiDAR on its lower part
CAR = 65  # the overtaken moving car


@pytest.fixture(scope="module")
def scene():
    return load_scene(sample_scene_path())


@pytest.fixture(scope="module")
def index(scene):
    return build_visibility_index(scene)


@pytest.fixture(scope="module")
def gt_points(scene):
    """Static surface points from the ground-truth depth of the training views (every 3rd pixel)."""
    views = scene.train_views
    depth = scene.load_depths(views)
    cams = scene.cameras(views)
    pts = backproject_depth(depth, cams.K, cams.cam_to_world)[:, :, ::3, ::3]
    ins = scene.load_instances(views)[:, ::3, ::3]
    img = scene.load_images(views)[:, :, ::3, ::3]
    valid = (depth[:, 0, ::3, ::3] > 0) & ~torch.isin(ins, torch.tensor(sorted(scene.tracks)))
    spacing = depth[:, 0, ::3, ::3] / cams.K[:, 0, 0, None, None] * 3
    return (
        pts.permute(0, 2, 3, 1)[valid],
        img.permute(0, 2, 3, 1)[valid],
        ins[valid],
        spacing[valid],
    )


def _model(scene, points, colors, spacing):
    n = points.shape[0]
    f = len(scene.frames)
    return GaussianModel(
        points,
        colors,
        torch.log(spacing)[:, None].expand(n, 3).clone(),
        torch.full((n,), -1),
        torch.zeros(0, f, 4, 4),
        torch.zeros(0, f, dtype=torch.bool),
        [],
        sh_degree=0,
        init_opacity=0.95,
    )


def _trainer(scene, model, index, **cfg):
    trainer = Trainer(
        scene,
        TrainConfig(iterations=100, checkpoint_every=10**6, vad=VisibilityDensifyConfig(**cfg)),
        model=model,
        progress=False,
    )
    trainer.strategy.index = index  # share the module's prebuilt index
    return trainer


def _flagged(rows, instance):
    sel = rows.instance == instance
    return rows.flagged[sel], rows.pixels[sel]


def _hits_on_car(scene, ref, points, instances):
    """Per other view of ``ref``'s camera with >= 50 of the object-frame ``points`` in the image
    (posed by the car's track at that frame): the fraction that lands on the car's mask."""
    track = scene.tracks[CAR]
    hits = []
    for v in scene.train_views:
        if scene.views[v].camera != scene.views[ref].camera or v == ref:
            continue
        o2w = track.object_to_world[scene.frame_position(scene.views[v].frame)]
        world = points @ o2w[:3, :3].T + o2w[:3, 3]
        cams = scene.cameras([v])
        uv, z = project_points(world[None], cams.K, cams.world_to_cam)
        h, w = cams.image_size
        u, vv = uv[0, :, 0].round().long(), uv[0, :, 1].round().long()
        ok = (z[0] > 0) & (u >= 0) & (u < w) & (vv >= 0) & (vv < h)
        if int(ok.sum()) >= 50:
            hits.append(float((instances(v)[vv[ok], u[ok]] == CAR).float().mean()))
    return hits


class TestIncompleteOnSample:
    def test_complete_geometry_is_not_flagged(self, scene, index, gt_points):
        pts, col, _, spc = gt_points
        trainer = _trainer(scene, _model(scene, pts, col, spc), index)
        rows, _ = trainer.strategy.detect()
        flagged, pixels = _flagged(rows, BUILDING)
        big = pixels >= 500
        assert int(big.sum()) >= 3
        # where the building is large in a view, its complete Gaussians pass the test
        assert float(flagged[big].float().mean()) <= 0.2

    def test_deleted_geometry_is_flagged_and_repopulated(self, scene, index, gt_points):
        pts, col, ins, spc = gt_points
        keep = ins != BUILDING
        trainer = _trainer(
            scene,
            _model(scene, pts[keep], col[keep], spc[keep]),
            index,
            max_instances=1,
            skip_classes=("road", "sidewalk", "tree", "car", "sign"),
            reconstruct=ReconstructConfig(max_crop=96, max_match_pixels=None),  # accuracy at full scale
        )
        rows, _ = trainer.strategy.detect()
        flagged, pixels = _flagged(rows, BUILDING)
        assert bool(flagged[pixels >= 500].all())
        n0 = trainer.model.num_gaussians
        event = trainer.strategy.densify(trainer.model.params, trainer.optimizer, trainer.state, 0)
        done = {e["instance"]: e for e in event["instances"]}
        assert BUILDING in done and done[BUILDING]["added"] > 200
        new = trainer.model.params["means"][n0:].detach()
        assert new.shape[0] == event["added"]
        # the new Gaussians lie on the deleted facade: distance to its true surface points
        target = pts[~keep]
        d = torch.cdist(new[::7], target).min(1).values
        assert float(d.median()) < 0.1
        assert float((d < 0.25).float().mean()) > 0.8
        # and the optimizer state grew with them
        for group in trainer.optimizer.param_groups:
            if group["name"] == "means":
                st = trainer.optimizer.state.get(group["params"][0])
                if st:
                    assert st["exp_avg"].shape[0] == trainer.model.num_gaussians


class TestMovingObject:
    def test_reconstruction_in_object_frame_follows_the_track(self, scene, index):
        ref = max(scene.train_views, key=lambda v: int((index.instances(v) == CAR).sum()))
        rec = reconstruct_instance(
            index, ref, CAR, ReconstructConfig(max_crop=96), torch.Generator().manual_seed(0)
        )
        assert rec.reason == "ok" and rec.track == CAR
        assert rec.points.shape[0] > 200
        # posed by the track at other frames, the points land on the car in those images
        hits = _hits_on_car(scene, ref, rec.points, index.instances)
        assert len(hits) >= 2
        assert min(hits) > 0.7

    def test_moving_object_gets_no_planar_completion(self, scene, index):
        ref = max(scene.train_views, key=lambda v: int((index.instances(v) == CAR).sum()))
        a, b = (
            reconstruct_instance(
                index, ref, CAR, ReconstructConfig(max_crop=64, planar=p), torch.Generator().manual_seed(1)
            )
            for p in (None, PlanarCompletionConfig(min_pixels=4, min_inlier_ratio=0.0))
        )
        assert a.points.shape[0] > 0
        torch.testing.assert_close(a.points, b.points)

    def test_new_gaussians_join_the_track_node(self, scene, index):
        ref = max(scene.train_views, key=lambda v: int((index.instances(v) == CAR).sum()))
        rec = reconstruct_instance(
            index, ref, CAR, ReconstructConfig(max_crop=64), torch.Generator().manual_seed(1)
        )
        t = scene.tracks[CAR]
        f = len(scene.frames)
        model = GaussianModel(
            torch.zeros(1, 3),
            torch.rand(1, 3),
            torch.zeros(1, 3),
            torch.full((1,), -1),
            t.object_to_world[None],
            t.valid[None],
            [CAR],
            sh_degree=0,
        )
        ctx = StrategyContext(lambda v: None, total_steps=1, steps_per_cycle=1, track_nodes={CAR: 0})
        vad = VisibilityAwareDensification()
        vad.prepare(context=ctx, index=index)
        ev = EventInputs(index, vad.inputs, ctx.render, None, vad.config, None, ctx.track_nodes, None)
        add_reconstructions(ev, model.params, None, None, [(CAR, ref, rec)], ctx.render, 1, 0)
        assert model.num_gaussians == 1 + rec.points.shape[0]
        assert (model.node_ids[1:] == 0).all()
        # the node's means are stored in the object frame and moved by the track's pose
        fpos = f - 1
        g = model.gaussians_at(fpos)
        o2w = t.object_to_world[fpos]
        expect = rec.points @ o2w[:3, :3].T + o2w[:3, 3]
        assert torch.allclose(g.means[g.ids >= 1].detach(), expect, atol=1e-4)


SIGN = 61  # the sample's traffic sign: about 100 pixels at half resolution


@pytest.fixture(scope="module")
def half():
    """The sample at half resolution (120×72) and its index: finer matching can go to 240×144."""
    scene = load_scene(sample_scene_path(), scale=0.5)
    return scene, build_visibility_index(scene)


class TestFinerMatchingOfSmallInstances:
    @staticmethod
    def _rel_error(rec, full):
        """Relative depth error of the points against the true depth of the files' resolution."""
        ref = rec.views[0]
        cams = full.cameras([ref])
        uv, z = project_points(rec.points[None], cams.K, cams.world_to_cam)
        gt = full.load_depths([ref])[0, 0]
        u, v = uv[0, :, 0].round().long(), uv[0, :, 1].round().long()
        ok = (u >= 0) & (u < gt.shape[1]) & (v >= 0) & (v < gt.shape[0])
        g, zz = gt[v[ok], u[ok]], z[0][ok]
        return ((zz - g).abs() / g)[g > 0]

    def test_sign_gets_more_points_as_accurate(self, half, scene):
        """Matching the sign at twice the scene's resolution gives many more points, as accurate.

        Measured: 12 → 253 points, median depth error 2.0 % → 2.2 % (supports 11, 15, 17, 23). With
        the voxels on the world's axes (before issue 31's ground frame) the sign had 15 voxels,
        view 0 was a support too, and the finer matching also halved the error (1.7 % → 0.75 %):
        on an instance of a dozen voxels the supports follow the voxels' discretisation. Since an
        event's pairs are matched together (each reference scoring only its own region): 0 → 190
        points, the scene's resolution giving no point of the sign at this seed (1 before); over
        PatchMatch seeds 0-5 the 2x matching keeps 121.5 consistent pixels on average (127.2 before).
        """
        half_scene, index = half
        ref = max(half_scene.train_views, key=lambda v: int((index.instances(v) == SIGN).sum()))
        recs = {
            up: reconstruct_instance(
                index, ref, SIGN, ReconstructConfig(max_upsample=up), torch.Generator().manual_seed(1)
            )
            for up in (1, 2)
        }
        n1, n2 = recs[1].points.shape[0], recs[2].points.shape[0]
        e1, e2 = self._rel_error(recs[1], scene), self._rel_error(recs[2], scene)
        assert n2 > 4 * max(n1, 1)
        assert float(e2.median()) < 0.03
        if e1.numel():  # the scene's resolution may give no point of the sign at all
            assert float(e2.median()) < 1.2 * float(e1.median())
        # depth priors stay at the scene's resolution, with depth where points came from
        assert recs[2].depth[0].shape == (1, *half_scene.image_size(ref))
        assert int((recs[2].depth[0] > 0).sum()) > 0
        assert recs[2].normal[0].shape == (3, *half_scene.image_size(ref))

    def test_large_instance_is_unchanged(self, half):
        half_scene, index = half
        ref = max(half_scene.train_views, key=lambda v: int((index.instances(v) == BUILDING).sum()))
        a, b = (
            reconstruct_instance(
                index, ref, BUILDING, ReconstructConfig(max_upsample=up), torch.Generator().manual_seed(1)
            )
            for up in (1, 2)
        )
        assert a.points.shape[0] > 100
        torch.testing.assert_close(a.points, b.points)

    def test_bad_factor_names_the_argument(self):
        with pytest.raises(ValueError, match="max_upsample"):
            ReconstructConfig(max_upsample=0)


class TestNormalsToQuats:
    def test_third_axis_is_the_normal(self):
        from vadgs.geometry import quaternion_to_rotation

        n = torch.nn.functional.normalize(torch.randn(50, 3), dim=-1)
        R = quaternion_to_rotation(normals_to_quats(n))
        assert torch.allclose(R[:, :, 2], n, atol=1e-5)


class TestRankInstances:
    def test_small_sign_is_not_starved_by_facades(self):
        # the street_a situation: many large flagged facades and one small sign
        px = {10 + i: 20_000 - 1000 * i for i in range(10)} | {61: 466}
        cls = {i: "building" for i in px} | {61: "sign"}
        assert 61 not in rank_instances(px, cls, "pixels")[:6]
        ranked = rank_instances(px, cls)
        assert ranked[:2] == [10, 61]
        assert sorted(ranked) == sorted(px)  # a permutation: nothing dropped or repeated

    def test_within_a_class_largest_first(self):
        px = {1: 5, 2: 50, 3: 500, 4: 7}
        cls = {1: "tree", 2: "tree", 3: "tree", 4: "sign"}
        assert rank_instances(px, cls) == [3, 4, 2, 1]

    def test_bad_ranking_names_the_argument(self):
        with pytest.raises(ValueError, match="ranking"):
            rank_instances({1: 3}, {}, "random")
        with pytest.raises(ValueError, match="ranking"):
            VisibilityDensifyConfig(ranking="random")


class TestPickReferences:
    def test_largest_first_then_another_camera_or_far_frame(self, scene):
        front = [v.index for v in scene.views if v.camera == "front"]
        left = [v.index for v in scene.views if v.camera == "front_left"]
        cands = [(front[0], 500), (front[1], 450), (left[0], 100), (front[4], 90)]
        assert pick_references(cands, scene, 1) == [front[0]]
        # front[1] is one frame after front[0] on the same camera: skipped for the other camera
        assert pick_references(cands, scene, 2) == [front[0], left[0]]
        assert pick_references(cands, scene, 3) == [front[0], left[0], front[4]]
        assert pick_references(cands, scene, 3, min_frame_gap=1) == [front[0], front[1], left[0]]
        assert pick_references([], scene, 2) == []

    def test_a_whole_view_replaces_the_last_reference(self, scene):
        front = [v.index for v in scene.views if v.camera == "front"]
        left = [v.index for v in scene.views if v.camera == "front_left"]
        cands = [(front[0], 500), (front[1], 450), (left[0], 100), (front[4], 90), (front[3], 80)]
        # none of the three largest shows the whole instance: the last becomes the largest whole one
        assert pick_references(cands, scene, 3, whole=[front[3]]) == [front[0], left[0], front[3]]
        # ... that keeps the frame gap to the others: front[1] does not (one frame from front[0])
        assert pick_references(cands, scene, 3, whole=[front[1]]) == [front[0], left[0], front[4]]
        assert pick_references(cands, scene, 3, whole=[left[0], front[3]]) == [front[0], left[0], front[4]]
        assert pick_references(cands, scene, 1, whole=[front[3]]) == [front[0]]  # one reference: the largest
        assert pick_references(cands, scene, 3, whole=[]) == [front[0], left[0], front[4]]


class TestWholeViews:
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

    def test_supports_of_a_whole_reference_show_it_whole(self, scene, index):
        from vadgs.select import ViewSelectionConfig
        from vadgs.train.vad.reconstruct import _select_supports
        from vadgs.train.vad.survey import instance_frame

        # the sample's short sequence: pairs (k = 2) with one shared voxel, so that groups form
        selection = ViewSelectionConfig(min_shared=1, k=2)
        maps = scene.load_instances(scene.train_views)
        changed = 0
        for k, ref in enumerate(scene.train_views):
            for inst in torch.unique(maps[k]).tolist():
                if inst <= 0 or int((maps[k] == inst).sum()) < 50 or index.cut_by_border(ref, inst):
                    continue
                frame = instance_frame(index, ref, inst, None, ReconstructConfig())
                if isinstance(frame, str):
                    continue
                sel = {
                    whole: _select_supports(
                        index,
                        ref,
                        inst,
                        None,
                        frame,
                        ReconstructConfig(whole_supports=whole, selection=selection),
                        torch.Generator().manual_seed(0),
                    ).views.tolist()
                    for whole in (False, True)
                }
                if sel[True] == sel[False] or len(sel[True]) < 2:  # no cut support chosen, or too
                    continue  # few whole views (then the selection among all views, its own draws)
                changed += 1
                assert len(sel[True]) == 2 and not any(index.cut_by_border(v, inst) for v in sel[True])
                assert any(index.cut_by_border(v, inst) for v in sel[False])
        assert changed >= 5  # 13 (reference, instance) pairs of the sample


class TestSeenSupports:
    """A static instance whose visibility sets give its reference nothing (the LiDAR of a real log hits
    a far facade only from closer frames) is selected on what the views' z-buffers show."""

    def _blind(self, index, ref):
        """The index with ``ref`` removed from every visibility set (its frame's LiDAR saw nothing)."""
        import dataclasses

        from vadgs.select import Covisibility

        cov = index.covis
        visible = [
            torch.zeros(0, dtype=torch.long) if v == ref else cov.voxels_of(v) for v in range(cov.num_views)
        ]
        blind = Covisibility.from_visible(
            visible, cov.voxel_centers, cov.world_to_cam, cov.camera_ids, cov.frame_ids
        )
        return dataclasses.replace(index, covis=blind)

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

    def test_blind_reference_is_selected_on_its_zbuffer(self, scene, index):
        ref = self._ref(scene, index)
        assert int((index.instances(ref) == BUILDING).sum()) > 100
        blind = self._blind(index, ref)
        cfg = ReconstructConfig(seen_supports=False)
        off = reconstruct_instance(blind, ref, BUILDING, cfg, torch.Generator().manual_seed(0))
        assert off.reason.startswith("selection:no_voxels") and off.points.shape[0] == 0
        on = reconstruct_instance(blind, ref, BUILDING, ReconstructConfig(), torch.Generator().manual_seed(0))
        assert len(on.views) == 5 and on.points.shape[0] > 100, on.reason
        # its points lie on the facade: as close to the ground truth as the unblinded reconstruction's
        full = reconstruct_instance(
            index, ref, BUILDING, ReconstructConfig(), torch.Generator().manual_seed(0)
        )
        assert full.reason == "ok" and on.points.shape[0] >= 0.3 * full.points.shape[0]

    def test_reference_seeing_one_voxel_asks_supports_to_share_it(self, scene, index):
        """A far cell of a real log's ground grid shows its reference one voxel: supports share that one."""
        from vadgs.select import ViewSelectionConfig, select_views
        from vadgs.train.vad.reconstruct import _select_supports
        from vadgs.train.vad.survey import instance_frame

        ref = self._ref(scene, index)
        blind = self._blind(index, ref)
        frame = instance_frame(blind, ref, BUILDING, None, ReconstructConfig())
        ids = torch.nonzero(frame.voxels).flatten()
        shown = ids[torch.isin(ids, index.seen_voxels(ref))].tolist()
        others = [v for v in scene.train_views if v != ref]

        def seen_by(vox):  # the training views whose z-buffer or visibility set hold the voxel
            return {
                v
                for v in others
                if vox in set(index.seen_voxels(v).tolist()) | set(index.covis.voxels_of(v).tolist())
            }

        vox = next(x for x in shown if len(seen_by(x)) >= 4)
        one = torch.zeros_like(frame.voxels)
        one[vox] = True
        one_frame = frame._replace(voxels=one)
        sel = _select_supports(
            blind, ref, BUILDING, None, one_frame, ReconstructConfig(), torch.Generator().manual_seed(0)
        )
        assert sel.reason == "ok (seen)" and len(sel.views) == 4
        assert set(sel.views.tolist()) <= seen_by(vox)
        # the selection's own rule (two shared voxels) finds nobody to share one voxel with
        covis = blind.seen_covis(one, [ref, *others])
        two = select_views(ref, covis, ViewSelectionConfig(min_shared=2), torch.Generator().manual_seed(0))
        assert two.reason.startswith("no_candidates") and len(two.views) == 0
        # a voxel no other view shows: no support, and the reason says the z-buffers were asked
        alone = next(x for x in shown if not seen_by(x))
        one = torch.zeros_like(frame.voxels)
        one[alone] = True
        sel = _select_supports(
            blind,
            ref,
            BUILDING,
            None,
            frame._replace(voxels=one),
            ReconstructConfig(),
            torch.Generator().manual_seed(0),
        )
        assert (
            len(sel.views) == 0 and sel.reason.startswith("no_candidates") and sel.reason.endswith("(seen)")
        )


class TestSeenSupportsOfATrack:
    """A moving object whose reference's LiDAR frame missed it (a real log's far car: its grid gathers the
    points of other frames) is selected on what the views' z-buffers show of its grid at their timestamp."""

    def _blind(self, index, ref):
        """The index with ``ref`` removed from the car's visibility sets (its frame's LiDAR missed it)."""
        import dataclasses

        from vadgs.select import Covisibility

        cov = index.track_covis[CAR]
        visible = [
            torch.zeros(0, dtype=torch.long) if v == ref else cov.voxels_of(v) for v in range(cov.num_views)
        ]
        blind = Covisibility.from_visible(
            visible, cov.voxel_centers, cov.world_to_cam, cov.camera_ids, cov.frame_ids
        )
        return dataclasses.replace(index, track_covis={**index.track_covis, CAR: blind})

    @staticmethod
    def _ref(scene, index):
        return max(scene.train_views, key=lambda v: int((index.instances(v) == CAR).sum()))

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

    def test_blind_track_reference_is_selected_on_its_zbuffer(self, scene, index):
        ref = self._ref(scene, index)
        blind = self._blind(index, ref)
        off = reconstruct_instance(
            blind, ref, CAR, ReconstructConfig(seen_supports=False), torch.Generator().manual_seed(0)
        )
        assert off.reason.startswith("selection:no_voxels") and off.points.shape[0] == 0
        on = reconstruct_instance(blind, ref, CAR, ReconstructConfig(), torch.Generator().manual_seed(0))
        assert on.reason == "ok (seen)" and on.track == CAR and len(on.views) == 5
        full = reconstruct_instance(index, ref, CAR, ReconstructConfig(), torch.Generator().manual_seed(0))
        assert full.reason == "ok" and on.points.shape[0] >= 0.5 * full.points.shape[0]
        # its points, in the car's frame, land on the car in the other views of the reference's camera
        hits = _hits_on_car(scene, ref, on.points, lambda v: scene.load_instances([v])[0])
        assert len(hits) >= 2 and min(hits) > 0.7, hits
