"""Tests of the benchmark-format loader (vadgs.data.scene_json.load_scene) and the Scene object."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from vadgs.data import LidarFrame, Scene, load_scene, sample_scene_path
from vadgs.geometry import Cameras, invert_rigid, project_points, scale_intrinsics

from .sample_copy import copy_sample_scene

SHARED = Path(__file__).resolve().parents[2].parent / "shared"
STREET_A = SHARED / "data" / "street_a"
needs_street_a = pytest.mark.skipif(
    not (STREET_A / "scene.json").is_file(), reason="needs ../shared/data/street_a"
)


@pytest.fixture(scope="module")
def sample() -> Scene:
    return load_scene(sample_scene_path())


def _lidar_vs_depth(scene: Scene, view_ids: list[int]) -> tuple[torch.Tensor, int]:
    """Relative error of LiDAR z-depth against GT depth at the nearest pixel, over valid hits."""
    errs = []
    depths = scene.load_depths(view_ids)
    cams = scene.cameras(view_ids)
    for b, vid in enumerate(view_ids):
        pts = scene.lidar(scene.views[vid].frame).points
        uv, z = project_points(pts[None], cams.K[b : b + 1], cams.world_to_cam[b : b + 1])
        uv, z = uv[0], z[0]
        H, W = scene.image_size(vid)
        px = uv.round().long()
        ok = (z > 0.1) & (px[:, 0] >= 0) & (px[:, 0] < W) & (px[:, 1] >= 0) & (px[:, 1] < H)
        gt = depths[b, 0, px[ok, 1], px[ok, 0]]
        valid = gt > 0
        errs.append((z[ok][valid] - gt[valid]).abs() / gt[valid])
    err = torch.cat(errs)
    return err, len(err)


class TestLoadSceneSample:
    def test_smoke(self, sample):
        assert isinstance(sample, Scene)
        assert repr(sample).startswith("Scene('street_a_sample', 8 frames, 24 views")

    def test_counts(self, sample):
        assert sample.num_views == 24 and len(sample.frames) == 8
        assert sample.camera_names == ["front", "front_left", "front_right"]
        assert [f.index for f in sample.frames] == list(range(16, 24))
        assert all(v.index == i for i, v in enumerate(sample.views))
        assert len(sample.tracks) == 3 and len(sample.instances) == 67
        assert sample.instance_ids("sign")
        assert all(sample.views[v].frame == 20 for v in sample.frames[4].view_ids)

    def test_split(self, sample):
        assert sample.test_frames == [18, 22]
        assert sample.train_frames == [16, 17, 19, 20, 21, 23]
        assert len(sample.test_views) == 6 and len(sample.train_views) == 18
        assert not set(sample.test_views) & set(sample.train_views)
        assert {sample.views[v].frame for v in sample.test_views} == {18, 22}

    def test_intrinsics_for_240x144(self, sample):
        for cam in sample.cameras_info.values():
            assert cam.image_size == (144, 240)
            # street_a at 480×288 has f = 384.080287, c = ((W-1)/2, (H-1)/2); halved: c' = (c + 0.5) / 2 - 0.5
            want = torch.tensor([[384.080287 / 2, 0, 119.5], [0, 384.080287 / 2, 71.5], [0, 0, 1]])
            torch.testing.assert_close(cam.K, want)

    def test_rescale(self):
        half = load_scene(sample_scene_path(), scale=0.5)
        full = load_scene(sample_scene_path())
        assert half.image_size(0) == (72, 120)
        torch.testing.assert_close(
            half.cameras_info["front"].K, scale_intrinsics(full.cameras_info["front"].K, 0.5)
        )
        assert half.load_images([0]).shape == (1, 3, 72, 120)
        assert half.load_depths([0]).shape == (1, 1, 72, 120)
        assert half.load_instances([0]).shape == (1, 72, 120)

    def test_load_images_at_another_size(self):
        half = load_scene(sample_scene_path(), scale=0.5)
        full = load_scene(sample_scene_path())
        # the files' own resolution from a half-resolution scene: the same pixels as a full load
        torch.testing.assert_close(half.load_images([3], size=(144, 240)), full.load_images([3]))
        with pytest.raises(ValueError, match="size"):
            half.load_images([3], size=(144.0, 240))

    def test_lazy_loading_shapes(self, sample):
        imgs = sample.load_images([0, 5])
        assert imgs.shape == (2, 3, 144, 240) and imgs.dtype == torch.float32
        assert 0 <= imgs.min() and imgs.max() <= 1 and imgs.std() > 0.01
        d = sample.load_depths([1])
        assert d.shape == (1, 1, 144, 240) and d.dtype == torch.float32 and (d > 0).any() and (d >= 0).all()
        ins = sample.load_instances([2])
        assert ins.shape == (1, 144, 240) and ins.dtype == torch.int64
        assert set(ins.unique().tolist()) - {0} <= set(sample.instances)
        lid = sample.lidar(16)
        assert isinstance(lid, LidarFrame)
        assert lid.points.shape == (12000, 3) and lid.points.dtype == torch.float32
        assert (
            lid.instance.shape == (12000,) and lid.instance.dtype == torch.int64 and lid.origin.shape == (3,)
        )

    def test_cameras(self, sample):
        cams = sample.cameras(sample.frames[0].view_ids)
        assert isinstance(cams, Cameras) and len(cams) == 3 and cams.image_size == (144, 240)
        torch.testing.assert_close(
            invert_rigid(cams.world_to_cam[1]), sample.views[1].cam_to_world, atol=1e-4, rtol=0
        )
        assert sample.view_id(17, "front_left") == 4
        with pytest.raises(KeyError):
            sample.view_id(99, "front")
        with pytest.raises(ValueError, match="view_ids"):
            sample.load_images([24])

    def test_lidar_agrees_with_gt_depth(self, sample):
        err, n = _lidar_vs_depth(sample, list(range(sample.num_views)))
        assert n > 10_000
        assert err.median() < 0.02
        assert (err < 0.05).float().mean() > 0.8

    def test_lidar_vs_depth_fails_with_wrong_pose(self, sample):
        # the same check with cam_to_world used as world_to_cam must fail
        cams = sample.cameras([0])
        pts = sample.lidar(16).points[None]
        uv, z = project_points(pts, cams.K, invert_rigid(cams.world_to_cam))
        ok = (
            (z[0] > 0.1)
            & (uv[0, :, 0] >= 0)
            & (uv[0, :, 0] < 239.5)
            & (uv[0, :, 1] >= 0)
            & (uv[0, :, 1] < 143.5)
        )
        d = sample.load_depths([0])[0, 0]
        px = uv[0, ok].round().long()
        gt = d[px[:, 1], px[:, 0]]
        rel = ((z[0, ok] - gt).abs() / gt.clamp(min=1e-3))[gt > 0]
        assert len(rel) == 0 or rel.median() > 0.1


class TestLoadSceneExceptions:
    def test_missing_scene_json(self, tmp_path):
        with pytest.raises(FileNotFoundError, match=r"no scene\.json"):
            load_scene(tmp_path)

    def test_malformed_json(self, tmp_path):
        root = copy_sample_scene(tmp_path)
        (root / "scene.json").write_text('{"cameras": [')
        with pytest.raises(ValueError, match="not valid JSON"):
            load_scene(root)

    def test_not_an_object(self, tmp_path):
        root = copy_sample_scene(tmp_path)
        (root / "scene.json").write_text("[1, 2]")
        with pytest.raises(ValueError, match="JSON object"):
            load_scene(root)

    @pytest.mark.parametrize(
        ("edit", "match"),
        [
            (lambda m: m.pop("cameras"), "missing key 'cameras'"),
            (lambda m: m.pop("frames"), "missing key 'frames'"),
            (lambda m: m["cameras"]["front"].pop("K"), r"cameras.front: missing key 'K'"),
            (
                lambda m: m["frames"][2]["views"][1].pop("cam_to_world"),
                r"frames\[2\].views\[1\]: missing key 'cam_to_world'",
            ),
            (
                lambda m: m["frames"][0]["views"][0].pop("image"),
                r"frames\[0\].views\[0\]: missing key 'image'",
            ),
            (lambda m: m["frames"][0].pop("index"), r"frames\[0\]: missing key 'index'"),
            (
                lambda m: m["cameras"]["front"].update(K=[[1, 0], [0, 1]]),
                r"cameras.front.K: expected shape \(3, 3\)",
            ),
            (lambda m: m["frames"][1]["views"][0].update(camera="rear"), "unknown camera 'rear'"),
        ],
    )
    def test_bad_entry(self, tmp_path, edit, match):
        with pytest.raises(ValueError, match=match):
            load_scene(copy_sample_scene(tmp_path, edit))

    def test_non_finite_pose(self, tmp_path):
        def edit(m: dict) -> None:
            m["frames"][3]["views"][2]["cam_to_world"][0][3] = float("nan")

        with pytest.raises(ValueError, match=r"frames\[3\].views\[2\].cam_to_world: expected finite"):
            load_scene(copy_sample_scene(tmp_path, edit))

    def test_missing_image_file(self, tmp_path):
        root = copy_sample_scene(tmp_path)
        (root / "images" / "front" / "019.png").unlink()
        with pytest.raises(FileNotFoundError, match=r"019\.png"):
            load_scene(root)
        scene = load_scene(root, check_files=False)  # loads, but the lazy read names the file
        with pytest.raises(FileNotFoundError, match=r"019\.png"):
            scene.load_images([scene.view_id(19, "front")])

    def test_missing_lidar_file(self, tmp_path):
        root = copy_sample_scene(tmp_path)
        (root / "lidar" / "020.npz").unlink()
        with pytest.raises(FileNotFoundError, match=r"020\.npz"):
            load_scene(root)

    def test_bad_scale(self):
        with pytest.raises(ValueError, match="scale"):
            load_scene(sample_scene_path(), scale=0)


@needs_street_a
class TestLoadSceneStreetA:
    @pytest.mark.parametrize(("scale", "size"), [(1.0, (288, 480)), (0.5, (144, 240))])
    def test_full_and_half(self, scale, size):
        scene = load_scene(STREET_A, scale=scale)
        assert len(scene.frames) == 40 and scene.num_views == 120 + 60  # + the novel views
        assert len(scene.train_views) + len(scene.test_views) == 120
        assert scene.image_size(0) == size
        assert scene.test_frames == list(range(2, 40, 4))
        assert len(scene.test_views) == 30
        assert scene.load_images([0]).shape == (1, 3, *size)
        assert scene.load_depths([0]).shape == (1, 1, *size)
        err, n = _lidar_vs_depth(scene, [scene.view_id(10, c) for c in scene.camera_names])
        assert n > 5_000 and err.median() < 0.02

    def test_half_matches_sample(self):
        half = load_scene(STREET_A, scale=0.5)
        sample = load_scene(sample_scene_path())
        torch.testing.assert_close(half.cameras_info["front"].K, sample.cameras_info["front"].K)
        torch.testing.assert_close(
            half.views[half.view_id(20, "front")].cam_to_world,
            sample.views[sample.view_id(20, "front")].cam_to_world,
        )


class TestNovelViews:
    def test_sample_has_none(self, sample):
        assert sample.novel_views == [] and sample.novel_groups() == {}
        assert all(v.group is None for v in sample.views)

    def test_parsed_and_kept_out_of_the_split(self, tmp_path):
        def add(meta):
            v = meta["frames"][1]["views"][0]
            meta["novel_views"] = [dict(v, frame=meta["frames"][1]["index"], shift_ego_m=[0, 2, 0])]

        base = load_scene(sample_scene_path())
        scene = load_scene(copy_sample_scene(tmp_path, add))
        assert scene.num_views == base.num_views + 1
        assert scene.novel_views == [base.num_views]
        assert scene.novel_groups() == {"shift+2.0": [base.num_views]}
        assert scene.train_views == base.train_views and scene.test_views == base.test_views
        assert [f.view_ids for f in scene.frames] == [f.view_ids for f in base.frames]
        assert scene.load_images(scene.novel_views).shape == (1, 3, 144, 240)

    def test_invisible_to_lidar_and_view_selection(self, tmp_path):
        from vadgs.data.lidar import accumulate_lidar
        from vadgs.train.vad import build_visibility_index

        def add(meta):
            meta["novel_views"] = [
                dict(v, frame=f["index"], shift_ego_m=[0, 2, 0]) for f in meta["frames"] for v in f["views"]
            ]

        base = load_scene(sample_scene_path())
        scene = load_scene(copy_sample_scene(tmp_path, add))
        a, b = accumulate_lidar(base), accumulate_lidar(scene)
        assert all(torch.equal(x, y) for x, y in zip(a.point_views, b.point_views))
        index = build_visibility_index(scene)
        assert not bool(index.allowed[scene.novel_views].any())  # never a source view of MVS
        assert torch.equal(index.allowed[: base.num_views], build_visibility_index(base).allowed)

    @pytest.mark.parametrize(
        ("edit", "match"),
        [
            (lambda m: m.update(novel_views={}), "novel_views: expected a list"),
            (lambda m: m.update(novel_views=[{"frame": 999}]), r"novel_views\[0\]\.frame"),
            (
                lambda m: m.update(
                    novel_views=[dict(m["frames"][0]["views"][0], frame=m["frames"][0]["index"])]
                ),
                "shift_ego_m",
            ),
        ],
    )
    def test_malformed(self, tmp_path, edit, match):
        with pytest.raises(ValueError, match=match):
            load_scene(copy_sample_scene(tmp_path, edit))

    @needs_street_a
    def test_street_a(self):
        scene = load_scene(STREET_A, scale=0.5)
        groups = scene.novel_groups()
        assert sorted(groups) == ["shift+2.0", "shift-2.0"] and len(scene.novel_views) == 60
        assert all(len(g) == 30 for g in groups.values())
        assert set(scene.novel_views).isdisjoint(scene.train_views + scene.test_views)
        for name, ids in groups.items():
            shift = torch.eye(4)
            shift[1, 3] = float(name.removeprefix("shift"))
            assert {(scene.views[v].frame, scene.views[v].camera) for v in ids} == {
                (scene.views[v].frame, scene.views[v].camera) for v in scene.test_views
            }
            for v in ids[:6]:
                info = scene.views[v]
                frame = scene.frames[scene.frame_position(info.frame)]
                expect = frame.ego_to_world @ shift @ scene.cameras_info[info.camera].cam_to_ego
                torch.testing.assert_close(info.cam_to_world, expect, atol=1e-5, rtol=0)
                test_view = scene.views[scene.view_id(info.frame, info.camera)]
                moved = info.cam_to_world[:3, 3] - test_view.cam_to_world[:3, 3]
                assert abs(float(moved.norm()) - 2.0) < 1e-4
        v = groups["shift-2.0"][0]
        assert scene.load_images([v]).shape == (1, 3, 144, 240)
        assert scene.load_depths([v]).shape == (1, 1, 144, 240)
        assert scene.load_instances([v]).shape == (1, 144, 240)
