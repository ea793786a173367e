from __future__ import annotations

import hashlib
import json

import pytest
import torch

from vadgs.data import load_scene, validate_scene
from vadgs.data.synthetic import SegmentConfig, make_segment
from vadgs.geometry.camera import invert_rigid, project_points

TINY = SegmentConfig(frames=4, cameras=2, width=64, height=48, lidar_points=2000)


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    return make_segment(tmp_path_factory.mktemp("seg") / "tiny", TINY, progress=False)


@pytest.fixture(scope="module")
def finer(tmp_path_factory):
    """Five cameras (two side ones at another height) at 160x120, for the geometric checks."""
    cfg = SegmentConfig(frames=3, cameras=5, width=160, height=120, side_height=90, lidar_points=6000)
    return make_segment(tmp_path_factory.mktemp("seg") / "finer", cfg, progress=False)


def _digest(folder) -> dict[str, str]:
    return {
        str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(folder.rglob("*"))
        if p.is_file()
    }


class TestMakeSegment:
    def test_smoke(self, tiny):
        scene = load_scene(tiny, validate="full")
        report = validate_scene(scene, full=True)
        assert report.ok, report.errors
        assert scene.load_images([0]).shape == (1, 3, 48, 64)  # JPEG images load

    def test_exception(self, tmp_path, tiny):
        with pytest.raises(ValueError, match="cameras"):
            SegmentConfig(cameras=6)
        with pytest.raises(ValueError, match="image_format"):
            make_segment(tmp_path / "x", TINY, image_format="gif", progress=False)
        with pytest.raises(ValueError, match="lidar_points"):
            make_segment(tmp_path / "x", TINY, lidar_points=0, progress=False)
        with pytest.raises(ValueError, match="not empty"):
            make_segment(tiny, TINY, progress=False)

    def test_cardinality(self, tiny, finer):
        scene = load_scene(tiny)
        assert scene.num_views == 8 and scene.camera_names == ["front", "front_left"]
        assert scene.test_frames == [2] and scene.train_frames == [0, 1, 3]
        assert all(len(scene.lidar(f.index).points) == 2000 for f in scene.frames)
        assert len(scene.tracks) == 3 and all(bool(t.valid.all()) for t in scene.tracks.values())
        classes = {i.class_name for i in scene.instances.values()}
        assert classes == {"road", "sidewalk", "building", "sign", "car"}
        assert all(t.mesh is not None and t.mesh.is_file() for t in scene.tracks.values())
        assert (tiny / "gt" / "static.ply").is_file()
        big = load_scene(finer)
        assert big.camera_names == ["front", "front_left", "front_right", "side_left", "side_right"]
        assert big.cameras_info["front"].image_size == (120, 160)
        assert big.cameras_info["side_left"].image_size == (90, 160)
        K = big.cameras_info["front"].K
        assert float(K[0, 2]) == pytest.approx(79.5) and float(K[1, 2]) == pytest.approx(59.5)

    def test_lidar_matches_depth_and_instances(self, finer):
        """A LiDAR point projected into a view lands where the GT depth and instance agree with it."""
        scene = load_scene(finer)
        checked = 0
        for group in scene.size_groups():
            cams = scene.cameras(group)
            depth, inst = scene.load_depths(group)[:, 0], scene.load_instances(group)
            h, w = cams.image_size
            for b, v in enumerate(group):
                lf = scene.lidar(scene.views[v].frame)
                uv, z = project_points(lf.points[None], cams.K[b : b + 1], cams.world_to_cam[b : b + 1])
                uv, z = uv[0], z[0]
                px = uv.round().long()
                # the projection of a point lies within half a pixel of a pixel centre only in a blur:
                # keep those close to one, whose ray is (nearly) the pixel's own
                close = (uv - px).abs().max(-1).values < 0.15
                ok = (z > 0.5) & close & (px[:, 0] >= 0) & (px[:, 0] < w) & (px[:, 1] >= 0) & (px[:, 1] < h)
                px, z, ids = px[ok], z[ok], lf.instance[ok]
                if len(z) == 0:
                    continue
                d = depth[b, px[:, 1], px[:, 0]]
                same = ((d - z).abs() / z < 0.03).float().mean()
                same_id = (inst[b, px[:, 1], px[:, 0]] == ids).float().mean()
                assert float(same) > 0.95 and float(same_id) > 0.95, (v, float(same), float(same_id))
                checked += len(z)
        assert checked > 300

    def test_moving_cars_follow_their_tracks(self, tiny):
        scene = load_scene(tiny)
        moved = 0
        for tid, track in scene.tracks.items():
            length, w, h = track.size_lwh.tolist()
            moved += float((track.object_to_world[-1, :3, 3] - track.object_to_world[0, :3, 3]).norm()) > 1.0
            for f in scene.frames:
                lf = scene.lidar(f.index)
                pts = lf.points[lf.instance == tid]
                local = pts @ invert_rigid(track.object_to_world[scene.frame_position(f.index)])[:3, :3].T
                local = local + invert_rigid(track.object_to_world[scene.frame_position(f.index)])[:3, 3]
                eps = 0.02
                inside = (local[:, 0].abs() <= length / 2 + eps) & (local[:, 1].abs() <= w / 2 + eps)
                inside &= (local[:, 2] >= -eps) & (local[:, 2] <= h + eps)
                assert bool(inside.all()), (tid, f.index)
        assert moved == 3
        hits = sum(int((scene.lidar(0).instance == tid).sum()) for tid in scene.tracks)
        assert hits > 0  # the cars are seen by the LiDAR

    def test_sign_boards_above_the_lidar(self, finer):
        scene = load_scene(finer)
        signs = scene.instance_ids("sign")
        assert signs
        for f in scene.frames:
            lf = scene.lidar(f.index)
            z = lf.points[torch.isin(lf.instance, torch.tensor(signs)), 2]
            assert bool((z < 5.3).all())  # the poles only
        ids = torch.tensor(signs)
        seen = sum(int(torch.isin(scene.load_instances(g), ids).sum()) for g in scene.size_groups())
        assert seen > 0  # the cameras see them

    def test_deterministic(self, tmp_path, tiny):
        again = make_segment(tmp_path / "again", TINY, progress=False)
        assert _digest(again) == _digest(tiny)
        other = make_segment(tmp_path / "other", TINY, seed=1, progress=False)
        a, b = _digest(tiny), _digest(other)
        assert a["gt/static.ply"] != b["gt/static.ply"]  # another street
        assert a["images/front/000.jpg"] != b["images/front/000.jpg"]

    def test_png_images(self, tmp_path):
        out = make_segment(tmp_path / "png", TINY, frames=1, image_format="png", progress=False)
        scene = load_scene(out, validate="full")
        assert scene.views[0].image.suffix == ".png"
        jpg = make_segment(tmp_path / "jpg", TINY, frames=1, progress=False)
        a = scene.load_images([0])
        b = load_scene(jpg).load_images([0])
        assert float((a - b).abs().mean()) < 0.03  # the same picture, JPEG-compressed

    def test_train_runs(self, finer, tmp_path):
        """A short ``vadgs train`` on five cameras of two image sizes."""
        from vadgs.cli import main

        out = tmp_path / "run"
        args = ["train", str(finer), "--out", str(out), "--iterations", "3", "--no-progress"]
        args += ["--init.max-points", "400", "--init.voxel-size", "1.0", "--init.sh-degree", "0"]
        assert main(args) == 0
        metrics = json.loads((out / "metrics.json").read_text())
        assert metrics["steps"] == 3 and metrics["test"]["num_views"] == 5
