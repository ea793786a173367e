from __future__ import annotations

import json

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from plyfile import PlyData

from vadgs.geometry.rotation import quaternion_to_rotation
from vadgs.render import eval_sh, load_ply
from vadgs.train.init import InitConfig, init_gaussians
from vadgs.train.results.export import (
    UP_AXES,
    equirect_directions,
    export_world,
    sky_equirect,
)


@pytest.fixture(scope="module")
def model(tiny_scene):
    torch.manual_seed(0)
    m = init_gaussians(
        tiny_scene, InitConfig(voxel_size=1.0, max_points=500, max_object_points=60, sh_degree=3)
    )
    m.active_sh_degree = 3
    with torch.no_grad():
        m.params["sh_rest"].normal_(0, 0.3)
        m.params["quats"].copy_(torch.randn_like(m.params["quats"]))
        m.params["opacity_logits"].normal_(0, 2)
        m.sky.normal_(0, 0.3)
    return m


def _frame_with_cars(model, scene) -> int:
    counts = model.track_valid.sum(0)
    return scene.frames[int(counts.argmax())].index


class TestSky:
    def test_mapping_matches_the_renderer(self, model):
        img = sky_equirect(model, 16, 32)
        assert img.shape == (3, 16, 32) and float(img.min()) >= 0 and float(img.max()) <= 1
        dirs = equirect_directions(16, 32)
        torch.testing.assert_close(
            dirs[8, 16], torch.tensor([1.0, 0, 0], dtype=torch.float64), atol=0.2, rtol=0
        )
        assert float(dirs[0, :, 2].min()) > 0.99  # the top row looks up
        for v, u in [(3, 5), (8, 16), (12, 30)]:
            # a 1x1 camera whose optical axis is the pixel's direction sees the same sky colour
            z = dirs[v, u].float()
            x = F.normalize(torch.linalg.cross(z, torch.tensor([0.3, 0.2, 0.9])), dim=0)
            c2w = torch.eye(4)
            c2w[:3, :3] = torch.stack([x, torch.linalg.cross(z, x), z], 1)
            K = torch.eye(3)[None]
            K[0, 0, 2] = K[0, 1, 2] = 0.0
            seen = model.sky_color(torch.linalg.inv(c2w)[None], K, (1, 1))[0, :, 0, 0]
            torch.testing.assert_close(img[:, v, u], seen.detach().clamp(0, 1), atol=1e-5, rtol=0)


class TestExportWorld:
    def test_read_back_equals_the_model(self, model, tiny_scene, tmp_path):
        frame = _frame_with_cars(model, tiny_scene)
        fpos = tiny_scene.frame_position(frame)
        out = export_world(model, tiny_scene, frame, tmp_path)
        g = model.gaussians_at(fpos)
        moving = model.node_ids[g.ids] >= 0
        assert bool(moving.any()) and out.num_gaussians == len(g.ids)
        v = PlyData.read(str(out.ply))["vertex"]
        col = lambda *names: torch.from_numpy(np.stack([v[n] for n in names], 1).astype(np.float64))  # noqa: E731
        assert v.count == len(g.ids) and len(v.properties) == 62  # degree 3: 45 f_rest
        torch.testing.assert_close(col("x", "y", "z"), g.means.double().detach(), atol=1e-5, rtol=0)
        torch.testing.assert_close(
            col("scale_0", "scale_1", "scale_2").exp(), g.scales.double().detach(), rtol=1e-5, atol=0
        )
        torch.testing.assert_close(
            torch.sigmoid(col("opacity")[:, 0]), g.opacities.double().detach(), atol=1e-5, rtol=0
        )
        q_file = F.normalize(col("rot_0", "rot_1", "rot_2", "rot_3"), dim=-1)
        q_model = F.normalize(g.quats.double().detach(), dim=-1)
        assert float((q_file * q_model).sum(-1).abs().min()) > 1 - 1e-6  # equal up to sign
        # colours: the file's SH at world directions = the model's (its frame's) at those directions
        sh = load_ply(out.ply).sh.double()
        gen = torch.Generator().manual_seed(0)
        for _ in range(3):
            d = F.normalize(torch.randn(len(g.ids), 3, generator=gen, dtype=torch.float64), dim=-1)
            local = (g.object_to_world_rot.double().transpose(-1, -2) @ d[:, :, None]).squeeze(-1)
            expect = eval_sh(g.sh.double().detach(), local, 3)
            torch.testing.assert_close(eval_sh(sh, d), expect, atol=1e-4, rtol=0)
        assert out.sky_png.is_file() and json.loads(out.sky_json.read_text())["sh_degree"] == model.sky_degree
        assert sorted(p.name for p in tmp_path.iterdir()) == sorted([out.ply.name, "sky.json", "sky.png"])

    def test_active_degree_and_inria_layout(self, model, tiny_scene, tmp_path):
        model.active_sh_degree = 1
        try:
            out = export_world(
                model, tiny_scene, tiny_scene.frames[2].index, tmp_path, inria=True, iteration=7
            )
        finally:
            model.active_sh_degree = 3
        assert out.ply == tmp_path / "point_cloud" / "iteration_7" / "point_cloud.ply"
        assert load_ply(out.ply).sh.shape[1] == 4
        cams = json.loads(out.cameras_json.read_text())
        recorded = [v for f in tiny_scene.frames for v in f.view_ids]
        assert len(cams) == len(recorded) == 24  # every camera, the rig's of the frame first
        assert {"position", "rotation", "fx", "fy", "width", "height"} <= set(cams[0])
        assert [c["img_name"] for c in cams[:3]] == [
            tiny_scene.views[v].image.stem for v in tiny_scene.frames[2].view_ids
        ]
        assert f"source_path={str(tiny_scene.root)!r}" in out.cfg_args.read_text()
        view = tiny_scene.views[tiny_scene.frames[2].view_ids[0]]
        np.testing.assert_allclose(cams[0]["position"], view.cam_to_world[:3, 3].numpy(), atol=1e-6)
        assert "sh_degree=1" in out.cfg_args.read_text()

    @pytest.mark.parametrize("up", ["-y", "y"])
    def test_up_axis_rotates_the_world_exactly(self, model, tiny_scene, up, tmp_path):
        """``up="-y"`` / ``"y"``: the file's points are the z-up export's rotated about x, exactly."""
        frame = _frame_with_cars(model, tiny_scene)
        ref = load_ply(export_world(model, tiny_scene, frame, tmp_path / "z").ply)
        out = load_ply(export_world(model, tiny_scene, frame, tmp_path / "up", up=up).ply)
        x, y, z = ref.means.unbind(-1)
        rotated = torch.stack([x, -z, y] if up == "-y" else [x, z, -y], -1)  # the scene's up (+z) on the axis
        assert torch.equal(out.means, rotated)  # a rotation of 0s and 1s: no rounding
        assert torch.equal(out.scales, ref.scales) and torch.equal(out.opacities, ref.opacities)
        R = torch.tensor(UP_AXES[up], dtype=torch.float64)
        torch.testing.assert_close(
            quaternion_to_rotation(out.quats.double()), R @ quaternion_to_rotation(ref.quats.double()),
            atol=1e-5, rtol=0,
        )  # fmt: skip
        d = F.normalize(torch.randn(len(ref.means), 3, dtype=torch.float64), dim=-1)
        torch.testing.assert_close(
            eval_sh(out.sh.double(), d @ R.T), eval_sh(ref.sh.double(), d), atol=1e-4, rtol=0
        )
        with pytest.raises(ValueError, match="up: expected one of z, y, -y, got 'x'"):
            export_world(model, tiny_scene, frame, tmp_path / "x", up="x")
        with pytest.raises(ValueError, match="up: expected 'z' with inria"):
            export_world(model, tiny_scene, frame, tmp_path / "i", up=up, inria=True)

    def test_unknown_frame(self, model, tiny_scene, tmp_path):
        with pytest.raises(KeyError, match="no frame 999"):
            export_world(model, tiny_scene, 999, tmp_path)
