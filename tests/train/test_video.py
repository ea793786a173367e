from __future__ import annotations

import imageio.v2 as imageio
import numpy as np
import pytest
import torch

from vadgs.render import quaternion_to_rotation
from vadgs.train.init import InitConfig, init_gaussians
from vadgs.train.video import (
    TIMELINE_ROWS,
    ego_trajectory,
    interpolate_rigid,
    model_at_time,
    object_poses_at,
    parse_trajectory,
    render_video,
)


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


def _rot(axis: torch.Tensor, angle: float) -> torch.Tensor:
    q = torch.cat([torch.tensor([np.cos(angle / 2)]), np.sin(angle / 2) * axis / axis.norm()])
    return quaternion_to_rotation(q.double())


class TestInterpolateRigid:
    def test_endpoints_and_midpoint(self):
        a, b = torch.eye(4, dtype=torch.float64), torch.eye(4, dtype=torch.float64)
        axis = torch.tensor([1.0, 2.0, 0.5], dtype=torch.float64)
        a[:3, :3], b[:3, :3] = _rot(axis, 0.3), _rot(axis, 1.1)
        a[:3, 3], b[:3, 3] = torch.tensor([1.0, 2, 3]), torch.tensor([3.0, 0, 3])
        torch.testing.assert_close(interpolate_rigid(a, b, 0.0), a)
        torch.testing.assert_close(interpolate_rigid(a, b, 1.0), b)
        mid = interpolate_rigid(a, b, 0.25)
        torch.testing.assert_close(mid[:3, :3], _rot(axis, 0.5))  # constant angular speed
        torch.testing.assert_close(mid[:3, 3], torch.tensor([1.5, 1.5, 3.0], dtype=torch.float64))

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
        import vadgs.train.video as video

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
