"""COLMAP projects as scenes: detection, hold-out, normalisation, model-to-scene matching."""

from __future__ import annotations

import dataclasses

import pytest
import torch

from vadgs.data import (
    find_colmap_model,
    load_colmap,
    match_colmap_views,
)
from vadgs.data.colmap import colmap_normalization, transform_colmap
from vadgs.data.normalize import (
    normalization_transform,
    similarity_scale,
    transform_cam_to_world,
    transform_points,
)
from vadgs.geometry import project_points

from .colmap_sample import write_sample_colmap

pycolmap = pytest.importorskip("pycolmap")


@pytest.fixture(scope="module")
def project(tmp_path_factory):
    root = tmp_path_factory.mktemp("colmap") / "proj"
    return root, write_sample_colmap(root)


class TestFindColmapModel:
    def test_detection(self, project, tmp_path):
        root, _ = project
        model = root / "sparse" / "0"
        assert find_colmap_model(root) == model  # a project folder
        assert find_colmap_model(model) == model  # the model folder itself
        assert find_colmap_model(root / "sparse") == model
        assert find_colmap_model(root / "images") is None  # no model there
        (tmp_path / "sparse").mkdir()
        (tmp_path / "sparse" / "cameras.txt").write_text("")
        assert find_colmap_model(tmp_path) is None  # cameras alone are not a model


class TestHoldOut:
    def test_every_eighth_by_name(self, project):
        root, syn = project
        scene, _ = load_colmap(root / "sparse" / "0", test_every=8)
        names = sorted(syn["names"])
        rel = [str(scene.views[v].image.relative_to(root / "images")) for v in scene.test_views]
        assert (
            rel
            == [names[i] for i in range(0, 24, 8)]
            == ["front/016.png", "front_left/016.png", "front_right/016.png"]
        )
        assert len(scene.train_views) == 21 and not set(scene.train_views) & set(scene.test_views)
        none, _ = load_colmap(root / "sparse" / "0")
        assert none.test_views == [] and len(none.train_views) == 24
        with pytest.raises(ValueError, match="test_every"):
            load_colmap(root / "sparse" / "0", test_every=-1)


class TestNormalization:
    def test_similarity_maps_cameras_as_stated(self, project):
        root, _ = project
        raw = load_colmap(root / "sparse" / "0")
        T = colmap_normalization(raw)
        s = similarity_scale(T)
        R = T[:3, :3] / s
        torch.testing.assert_close(R @ R.T, torch.eye(3, dtype=torch.float64), atol=1e-9, rtol=0)
        assert float(torch.linalg.det(R)) == pytest.approx(1.0)
        scene, points = transform_colmap(raw, T)
        c2w = torch.stack([v.cam_to_world for v in scene.views]).double()
        centres = c2w[:, :3, 3]
        torch.testing.assert_close(centres.mean(0), torch.zeros(3, dtype=torch.float64), atol=1e-5, rtol=0)
        up = -c2w[:, :3, 1].mean(0)
        torch.testing.assert_close(
            up / up.norm(), torch.tensor([0.0, 0, 1], dtype=torch.float64), atol=1e-6, rtol=0
        )
        # the median camera-to-point depth of the TRACK table is 10
        cams = scene.cameras(points.view_idx.tolist())
        _, z = project_points(points.points[points.point_idx][:, None], cams.K, cams.world_to_cam)
        assert float(z.median()) == pytest.approx(10.0, rel=1e-3)
        # the sample is in metres with cameras 1.5 m up: the scale is the depth ratio, not 1
        raw_cams = raw.scene.cameras(points.view_idx.tolist())
        _, z_raw = project_points(
            raw.points.points[points.point_idx][:, None], raw_cams.K, raw_cams.world_to_cam
        )
        assert s == pytest.approx(10.0 / float(z_raw.median()), rel=1e-3)
        # pixels do not move: every observation reprojects as before
        uv_raw, _ = project_points(
            raw.points.points[points.point_idx][:, None], raw_cams.K, raw_cams.world_to_cam
        )
        uv_new, _ = project_points(points.points[points.point_idx][:, None], cams.K, cams.world_to_cam)
        assert float((uv_raw - uv_new).abs().max()) < 1e-3
        assert scene.sfm_points is points

    def test_load_normalize_true_equals_recorded_transform(self, project):
        root, _ = project
        a = load_colmap(root / "sparse" / "0", normalize=True)
        T = colmap_normalization(load_colmap(root / "sparse" / "0"))
        b = load_colmap(root / "sparse" / "0", normalize=T.tolist())  # as a run records it (JSON)
        for va, vb in zip(a.scene.views, b.scene.views):
            assert torch.equal(va.cam_to_world, vb.cam_to_world)
        assert torch.equal(a.points.points, b.points.points)

    def test_reference_example(self):
        # two cameras along +z at x = 0 and 2, one point 5 deep: centre (1, 0, 0) -> 0, depth 5 -> 10
        c2w = torch.eye(4, dtype=torch.float64).repeat(2, 1, 1)
        c2w[1, 0, 3] = 2.0
        T = normalization_transform(
            c2w, torch.tensor([[1.0, 0, 5]]), (torch.tensor([0, 0]), torch.tensor([0, 1]))
        )
        torch.testing.assert_close(transform_points(T, torch.tensor([[1.0, 0, 5]], dtype=torch.float64)),
                                   torch.tensor([[0.0, 10.0, 0.0]], dtype=torch.float64))  # fmt: skip
        new = transform_cam_to_world(T, c2w)
        torch.testing.assert_close(
            new[:, :3, 3], torch.tensor([[-2.0, 0, 0], [2.0, 0, 0]], dtype=torch.float64)
        )
        torch.testing.assert_close(new[0, :3, 2], torch.tensor([0.0, 1, 0], dtype=torch.float64))  # forward

    def test_no_points_uses_camera_spread(self):
        c2w = torch.eye(4, dtype=torch.float64).repeat(3, 1, 1)
        c2w[:, 0, 3] = torch.tensor([0.0, 1.0, 2.0])
        T = normalization_transform(c2w, target_depth=10.0)
        assert similarity_scale(T) == pytest.approx(10.0)  # median distance from the centre is 1
        assert similarity_scale(normalization_transform(c2w[:1])) == 1.0

    def test_exception(self, project):
        root, _ = project
        with pytest.raises(ValueError, match="normalize: expected a finite"):
            load_colmap(root / "sparse" / "0", normalize=torch.eye(3))
        with pytest.raises(ValueError, match="not a similarity"):
            load_colmap(root / "sparse" / "0", normalize=torch.diag(torch.tensor([1.0, 2.0, 1.0, 1.0])))
        with pytest.raises(ValueError, match="target_depth"):
            normalization_transform(torch.eye(4)[None], target_depth=0.0)
        with pytest.raises(ValueError, match="cam_to_world"):
            normalization_transform(torch.eye(4))


class TestMatchColmapViews:
    def test_matching_model(self, project):
        root, syn = project
        idx = match_colmap_views(syn["scene"], root / "sparse" / "0", "--colmap")
        names = sorted(syn["names"])
        assert [syn["names"][i] for i in idx.tolist()] == names

    def test_other_names(self, tmp_path, project):
        _, syn = project
        write_sample_colmap(tmp_path / "p", n_points=50, link_images=False, name_prefix="castle_")
        with pytest.raises(
            ValueError,
            match=r"--colmap .*24 of 24 registered image names match none \(expected names like \['front/016",
        ):
            match_colmap_views(syn["scene"], tmp_path / "p" / "sparse" / "0", "--colmap")

    def test_other_world_frame(self, tmp_path, project):
        _, syn = project
        write_sample_colmap(tmp_path / "p", n_points=50, link_images=False, shift=(5.0, 0.0, 0.0))
        with pytest.raises(ValueError, match=r"not in the world frame .* median 5 from the scene's"):
            match_colmap_views(syn["scene"], tmp_path / "p" / "sparse" / "0", "--colmap")


def test_scene_keeps_sfm_points_through_replace(project):
    root, _ = project
    scene, points = load_colmap(root / "sparse" / "0")
    assert scene.sfm_points is points and "1500 SfM points" in repr(scene)
    assert dataclasses.replace(scene, name="x").sfm_points is points
