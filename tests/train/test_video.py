from __future__ import annotations

import dataclasses
import re

import imageio.v2 as imageio
import pytest
import torch

from vadgs.data.scene import CameraInfo, FrameInfo, Scene, ViewInfo
from vadgs.train.init import InitConfig, init_gaussians
from vadgs.train.results.trajectory import (
    INTERPOLATE_BETWEEN,
    ORBIT_FRAMES,
    default_video_camera,
    ego_trajectory,
    interpolated_trajectory,
    make_trajectory,
    orbit_trajectory,
    parse_trajectory,
    scene_up,
    trajectory_choices,
)
from vadgs.train.results.video import (
    TIMELINE_ROWS,
    depth_percentiles,
    model_at_time,
    object_poses_at,
    render_video,
    video_frame,
)

from ..data.photo_sample import SIDEWAYS, photo_cameras, sideways


@pytest.fixture(scope="module")
def tiny_model(tiny_scene):
    torch.manual_seed(0)
    model = init_gaussians(
        tiny_scene, InitConfig(voxel_size=1.0, max_points=600, max_object_points=80, sh_degree=1)
    )
    model.active_sh_degree = 1
    with torch.no_grad():
        model.params["sh_rest"].normal_(0, 0.2)
    return model


class TestObjectPoses:
    def test_object_poses(self):
        o2w = torch.eye(4).repeat(2, 3, 1, 1)
        o2w[:, 1, 0, 3] = 2.0
        valid = torch.tensor([[True, True, True], [True, False, True]])
        poses, ok = object_poses_at(o2w, valid, 0.5)
        assert poses[0, 0, 3] == 1.0 and ok.tolist() == [True, False]  # nearest frame (1) for track 1
        poses, ok = object_poses_at(o2w, valid, 0.4)
        assert ok.tolist() == [True, True] and poses[1, 0, 3] == 0.0
        with pytest.raises(ValueError, match="time"):
            object_poses_at(o2w, valid, 2.5)


class TestTrajectory:
    def test_parse(self):
        assert parse_trajectory("shift:2") == (0.0, 2.0, 0.0)
        with pytest.raises(ValueError, match="trajectory"):
            parse_trajectory("orbit")

    def test_ego_poses_match_views(self, tiny_scene):
        traj = ego_trajectory(tiny_scene, "front_left", frames_between=2)
        assert len(traj.time) == (len(tiny_scene.frames) - 1) * 3 + 1
        for i, f in enumerate(tiny_scene.frames):
            view = tiny_scene.views[tiny_scene.view_id(f.index, "front_left")]
            torch.testing.assert_close(traj.cam_to_world[3 * i], view.cam_to_world, atol=1e-5, rtol=0)

    def test_shift_is_in_the_ego_frame(self, tiny_scene):
        plain = ego_trajectory(tiny_scene, "front")
        left = ego_trajectory(tiny_scene, "front", (0, 2, 0))
        e2w = tiny_scene.frames[3].ego_to_world
        torch.testing.assert_close(left.cam_to_world[3, :3, 3] - plain.cam_to_world[3, :3, 3], 2 * e2w[:3, 1])

    def test_bad_inputs(self, tiny_scene):
        with pytest.raises(ValueError, match="camera"):
            ego_trajectory(tiny_scene, "rear")
        with pytest.raises(ValueError, match="frames_between"):
            ego_trajectory(tiny_scene, "front", frames_between=-1)


class TestModelAtTime:
    def test_integer_time_renders_as_the_model(self, tiny_model, tiny_scene):
        v = tiny_scene.test_views[1]
        cams = tiny_scene.cameras([v])
        frame = tiny_scene.view_frame_position(v)
        with torch.no_grad():
            ref = tiny_model.render(cams.world_to_cam, cams.K, cams.image_size, frame)
            out = model_at_time(tiny_model, float(frame)).render(
                cams.world_to_cam, cams.K, cams.image_size, 0
            )
        torch.testing.assert_close(out.color, ref.color)
        assert tiny_model.object_to_world.shape[1] == len(tiny_scene.frames)  # the model is untouched

    def test_cars_move_between_frames(self, tiny_model):
        g0 = model_at_time(tiny_model, 2.0).gaussians_at(0)
        g1 = model_at_time(tiny_model, 2.5).gaussians_at(0)
        g2 = model_at_time(tiny_model, 3.0).gaussians_at(0)
        assert torch.equal(g0.ids, g1.ids) and torch.equal(g1.ids, g2.ids)
        moving = tiny_model.node_ids[g0.ids] >= 0
        assert bool(moving.any())
        torch.testing.assert_close(g1.means[~moving], g0.means[~moving])
        torch.testing.assert_close(
            g1.means[moving], (g0.means[moving] + g2.means[moving]) / 2, atol=1e-4, rtol=0
        )


class TestRenderVideo:
    def test_written_and_readable(self, tiny_model, tiny_scene, tmp_path):
        traj = ego_trajectory(tiny_scene, "front", (0, -2, 0), frames_between=1)
        info = render_video(tiny_model, tiny_scene, tmp_path / "v.mp4", traj, fps=5, progress=False)
        h, w = tiny_scene.cameras_info["front"].image_size
        rows = h + TIMELINE_ROWS
        assert info.num_frames == 15 and info.size == (rows + rows % 2, 3 * w + w % 2)
        with imageio.get_reader(info.path, format="FFMPEG") as reader:
            frames = [f for f in reader]  # not list(reader): its len() is inf
        assert len(frames) == 15 and frames[0].shape == (*info.size, 3)
        assert frames[0].std() > 5  # not blank
        assert [p.name for p in tmp_path.iterdir()] == ["v.mp4"]  # no temporary left behind
        # the timeline bar: white up to the frame's position (video compression blurs its edge)
        bar_first, bar_last = frames[0][h + 1, :, 0].astype(int), frames[-1][h + 1, :, 0].astype(int)
        assert bar_first[-20:].mean() < 120 and bar_last[-20:].mean() > 200

    def test_interrupted_video_keeps_the_previous_file(self, tiny_model, tiny_scene, tmp_path, monkeypatch):
        """A failure mid-video (here at the third frame) leaves the previous file and no temporary."""
        import vadgs.train.results.video as video

        path = tmp_path / "v.mp4"
        path.write_bytes(b"previous")
        frame = video.video_frame
        calls = []

        def failing(*args, **kwargs):
            calls.append(1)
            if len(calls) == 3:
                raise KeyboardInterrupt
            return frame(*args, **kwargs)

        monkeypatch.setattr(video, "video_frame", failing)
        traj = ego_trajectory(tiny_scene, "front")
        with pytest.raises(KeyboardInterrupt):
            render_video(tiny_model, tiny_scene, path, traj, fps=5, progress=False)
        assert len(calls) == 3
        assert [p.name for p in tmp_path.iterdir()] == ["v.mp4"] and path.read_bytes() == b"previous"


class TestVideoLayout:
    def test_color_layout_is_the_strips_colour_panel(self, tiny_model, tiny_scene):
        v = tiny_scene.test_views[0]
        cams = tiny_scene.cameras([v])
        with torch.no_grad():
            out = tiny_model.render(cams.world_to_cam, cams.K, cams.image_size, 0)
        h, w = cams.image_size
        strip = video_frame(out, (1.0, 50.0), 0.5)
        color = video_frame(out, None, 0.5, layout="color")
        assert strip.shape == (h + TIMELINE_ROWS, 3 * w, 3) and color.shape == (h + TIMELINE_ROWS, w, 3)
        assert (color[:h] == strip[:h, :w]).all()  # the same pixels, the same bar
        with pytest.raises(ValueError, match="layout: expected one of strip, color, got 'depth'"):
            video_frame(out, layout="depth")

    def test_color_video_and_one_depth_range_over_the_path(
        self, tiny_model, tiny_scene, tmp_path, monkeypatch
    ):
        """The depth range is the widest of the frames along the path, not the first frame's."""
        import vadgs.train.results.video as video

        traj = ego_trajectory(tiny_scene, "front")  # 8 poses: every one is a depth sample
        info = render_video(tiny_model, tiny_scene, tmp_path / "c.mp4", traj, progress=False, layout="color")
        h, w = tiny_scene.cameras_info["front"].image_size
        assert info.num_frames == 8 and info.size == (h + TIMELINE_ROWS + (h + TIMELINE_ROWS) % 2, w + w % 2)
        ranges = []
        for c2w, t in zip(traj.cam_to_world, traj.time.tolist()):
            w2c = torch.linalg.inv(c2w[None])
            K = tiny_scene.cameras_info["front"].K[None]
            with torch.no_grad():
                ranges.append(depth_percentiles(model_at_time(tiny_model, t).render(w2c, K, (h, w), 0)))
        expected = (min(r[0] for r in ranges), max(r[1] for r in ranges))
        assert expected != ranges[0]  # the path's frames differ: the first frame's range is narrower
        seen = []
        frame = video.video_frame
        monkeypatch.setattr(video, "video_frame", lambda r, d, *a: seen.append(d) or frame(r, d, *a))
        render_video(tiny_model, tiny_scene, tmp_path / "s.mp4", traj, progress=False)
        assert len(seen) == 8 and set(seen) == {seen[0]}
        assert seen[0] == pytest.approx(expected, rel=1e-5)


# -- camera paths of photo collections ---------------------------------------------------------------


def _photo_scene() -> Scene:
    """The room's 10 photo cameras (one rolled 90°, one larger) as a scene: a photo per frame."""
    cams = photo_cameras()
    c2w, K, size = sideways(cams["cam_to_world"][SIDEWAYS], cams["K"][SIDEWAYS], cams["sizes"][SIDEWAYS])
    cams["cam_to_world"][SIDEWAYS], cams["K"][SIDEWAYS], cams["sizes"][SIDEWAYS] = c2w, K, size
    info, frames, views = {}, [], []
    for i, (m, k, hw) in enumerate(zip(cams["cam_to_world"], cams["K"], cams["sizes"])):
        name = f"camera_{i + 1}"
        info[name] = CameraInfo(name, torch.tensor(k, dtype=torch.float32), hw, None)
        views.append(ViewInfo(i, i, name, float(i), torch.tensor(m, dtype=torch.float32)))
        frames.append(FrameInfo(i, float(i), None, (i,)))
    return Scene("room", None, info, frames, views, train_frames=list(range(10)))


UP = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)


class TestPhotoPaths:
    def test_scene_up_ignores_a_sideways_photo(self, tiny_scene):
        scene = _photo_scene()
        torch.testing.assert_close(scene_up(scene), UP, atol=1e-6, rtol=0)
        # the mean of the cameras' -y alone would lean towards the sideways camera's
        mean = torch.stack([-v.cam_to_world[:3, 1].double() for v in scene.views]).mean(0)
        assert float(torch.rad2deg(torch.acos(mean @ UP / mean.norm()))) > 3
        # a street rig: up is the ego frame's z (the sample's cameras look level)
        up = scene_up(tiny_scene)
        ez = tiny_scene.frames[0].ego_to_world[:3, 2].double()
        assert float(up @ ez) > 0.999

    def test_interpolated_path_through_the_cameras(self):
        scene = _photo_scene()
        traj = interpolated_trajectory(scene, frames_between=3)
        assert traj.cam_to_world.shape == (37, 4, 4) and traj.camera == "camera_1"
        torch.testing.assert_close(traj.time, torch.arange(37, dtype=torch.float64) / 4)
        for i, v in enumerate(scene.views):
            pose = traj.cam_to_world[4 * i]
            torch.testing.assert_close(pose[:3, 3], v.cam_to_world[:3, 3], atol=1e-5, rtol=0)
            torch.testing.assert_close(pose[:3, 2], v.cam_to_world[:3, 2], atol=1e-5, rtol=0)
        # never rolled, not even at the sideways photo: x stays horizontal, y points down
        assert float((traj.cam_to_world[:, :3, 0] @ UP.float()).abs().max()) < 1e-5
        assert bool((traj.cam_to_world[:, :3, 1] @ UP.float() < 0).all())
        # between the cameras: on the arc's side of the box (radius ~3), looking at it
        r = traj.cam_to_world[:, :2, 3].norm(dim=-1)
        assert float(r.min()) > 2.9 and float(r.max()) < 3.05

    def test_orbit_around_the_centre(self):
        scene = _photo_scene()
        traj = orbit_trajectory(scene, num_frames=24)
        centre = torch.tensor([0.0, 0.0, 0.7])
        pos = traj.cam_to_world[:, :3, 3]
        torch.testing.assert_close(pos[:, :2].norm(dim=-1), torch.full((24,), 3.0), atol=1e-4, rtol=0)
        heights = torch.stack([v.cam_to_world[2, 3] for v in scene.views])
        torch.testing.assert_close(pos[:, 2], torch.full((24,), float(heights.mean())), atol=1e-4, rtol=0)
        forward = torch.nn.functional.normalize(centre - pos, dim=-1)
        torch.testing.assert_close(traj.cam_to_world[:, :3, 2], forward, atol=1e-4, rtol=0)
        azimuth = torch.rad2deg(torch.atan2(pos[:, 1], pos[:, 0]))
        assert float(azimuth[0]) == pytest.approx(-70.0, abs=1e-3)  # at the first photo
        assert float(azimuth[1] - azimuth[0]) == pytest.approx(15.0, abs=1e-3)  # turning as they do
        assert traj.time.tolist() == pytest.approx(torch.linspace(0, 9, 24).tolist())

    def test_choices_and_errors(self, tiny_scene):
        scene = _photo_scene()
        assert default_video_camera(scene) == "camera_1"
        assert trajectory_choices(scene) == ["interpolate", "orbit", "orbit:FRAMES"]
        assert len(make_trajectory(scene).time) == 9 * (INTERPOLATE_BETWEEN + 1) + 1  # the default
        assert len(make_trajectory(scene, "orbit").time) == ORBIT_FRAMES
        offered = "it offers ['interpolate', 'orbit', 'orbit:FRAMES']"
        for spec, message in [
            ("ego", "has no ego path for camera 'camera_1' (no ego poses, no view of it at every frame)"),
            ("shift:2", "has no ego path for camera 'camera_1' (no ego poses)"),
            ("orbit:0", "expected orbit:FRAMES with FRAMES >= 1"),
            ("spiral", "trajectory: expected one of ['interpolate', 'orbit', 'orbit:FRAMES'], got 'spiral'"),
        ]:
            with pytest.raises(ValueError, match=re.escape(message)):
                make_trajectory(scene, spec)
        with pytest.raises(ValueError, match=re.escape(offered)):
            ego_trajectory(scene, "camera_1")
        # one camera in every frame (a one-camera photo collection): ego is offered, not the default
        one = dataclasses.replace(scene, cameras_info={"camera_1": scene.cameras_info["camera_1"]})
        one.views = [dataclasses.replace(v, camera="camera_1") for v in scene.views]
        assert trajectory_choices(one) == ["interpolate", "ego", "orbit", "orbit:FRAMES"]
        assert len(make_trajectory(one, "ego").time) == 10
        # a rig with ego poses keeps the ego path as its default
        assert make_trajectory(tiny_scene).time.tolist() == list(range(8))
        assert trajectory_choices(tiny_scene)[:3] == ["ego", "shift:METRES", "shift:X,Y,Z"]


@pytest.fixture(scope="module")
def colmap_run(tmp_path_factory):
    """A 2-step run on the sample as a COLMAP project (24 photos, 3 cameras, every 8th held out)."""
    from vadgs.cli import main

    from ..data.colmap_sample import write_sample_colmap

    pytest.importorskip("pycolmap")
    root = tmp_path_factory.mktemp("colmap_video")
    write_sample_colmap(root / "proj", n_points=300)
    fast = ["--scale", "0.25", "--no-progress", "--init.sh-degree", "0", "--init.max-points", "300"]
    argv = ["--threads", "1", "train", str(root / "proj"), "--out", str(root / "run"), "--iterations", "2"]
    assert main([*argv, *fast]) == 0
    return root / "run"


class TestColmapRunWords:
    def test_photos_are_spoken_of_as_photos(self, colmap_run, capsys):
        """A photo collection's lines say photos, and leave out PSNR* (moving objects) or say why."""
        import json

        from vadgs.cli import main
        from vadgs.cli._common import metrics_summary

        metrics = json.loads((colmap_run / "metrics.json").read_text())
        assert metrics["test"]["psnr_star"] is None and metrics["gaussians_per_node"].keys() == {"static"}
        line = metrics_summary(metrics)
        assert "test PSNR" in line and "PSNR*" not in line
        assert main(["--threads", "1", "eval", str(colmap_run), "--no-progress"]) == 0
        said = capsys.readouterr().out
        assert "psnr_star: null: PSNR* scores moving objects only, and photos have none" in said


class TestColmapRunVideo:
    def test_render_video_of_a_photo_collection(self, colmap_run, capsys):
        from vadgs.cli import main

        out = colmap_run / "v.mp4"
        argv = ["--threads", "1", "render", str(colmap_run), "--no-progress"]
        assert main([*argv, "--video", str(out), "--frames-between", "1"]) == 0  # the default: interpolate
        said = capsys.readouterr().out
        assert (
            "41 frames" in said and "(trajectory interpolate, camera camera_1)" in said
        )  # 21 training photos
        with imageio.get_reader(out, format="FFMPEG") as reader:
            frames = [f for f in reader]
        assert len(frames) == 41 and frames[0].shape == (36 + TIMELINE_ROWS, 3 * 60, 3)
        assert main([*argv, "--video", str(out), "--trajectory", "orbit:6", "--camera", "camera_2"]) == 0
        assert "6 frames" in capsys.readouterr().out
        assert main([*argv, "--video", str(out), "--trajectory", "orbit:4", "--video-layout", "color"]) == 0
        assert "4 frames of 60x40 at" in capsys.readouterr().out  # the colour alone (and the bar)
        with imageio.get_reader(out, format="FFMPEG") as reader:
            assert [f.shape for f in reader] == [(36 + TIMELINE_ROWS, 60, 3)] * 4
        assert main([*argv, "--trajectory", "list"]) == 0
        said = capsys.readouterr().out
        assert "trajectories of scene 'proj', camera camera_1: interpolate, orbit, orbit:FRAMES" in said
        assert "default: interpolate" in said
        for flags, message in [
            (["--trajectory", "ego"], "--trajectory: scene 'proj' has no ego path for camera 'camera_1'"),
            (["--trajectory", "shift:1"], "--trajectory: scene 'proj' has no ego path"),
            (["--camera", "front"], "--camera: expected one of ['camera_1', 'camera_2', 'camera_3']"),
            (["--trajectory", "orbit", "--frames-between", "2"], "--frames-between: not used by orbit"),
        ]:
            assert main([*argv, "--video", str(out), *flags]) == 2
            err = capsys.readouterr().err
            assert message in err and err.count("\n") == 1, err
