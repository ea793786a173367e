"""The web viewer (vadgs.viewer, ``vadgs view``): data preparation, the viser scene, a real browser."""

from __future__ import annotations

import math
import socket
import subprocess
import sys
import time

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from vadgs.render import rgb_to_sh
from vadgs.train.config import TrainConfig
from vadgs.train.init import InitConfig
from vadgs.train.strategy import DefaultStrategyConfig
from vadgs.train.trainer import Trainer
from vadgs.viewer import (
    FILTERS,
    browser_screenshot,
    build_viewer,
    find_chromium,
    frame_frusta,
    node_pose,
    splat_arrays,
    viewer_groups,
)

viser = pytest.importorskip("viser")

CHROMIUM = find_chromium()
needs_chromium = pytest.mark.skipif(CHROMIUM is None, reason="no Chromium on this machine")


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="module")
def run(tiny_scene, tmp_path_factory):
    """A 4-step run of the tiny scene with a third of its Gaussians marked as added by event 1 / 2."""

    config = TrainConfig(
        iterations=4,
        init=InitConfig(voxel_size=0.6, max_points=1500, max_object_points=150, sh_degree=1),
        strategy=DefaultStrategyConfig(refine_start_iter=100),
        checkpoint_every=0,
    )
    out = tmp_path_factory.mktemp("view_run")
    ref = {"kind": "benchmark", "path": str(tiny_scene.root), "scale": 0.25}
    trainer = Trainer(tiny_scene, config, out_dir=out, progress=False, scene_ref=ref)
    trainer.train()
    model = trainer.model
    n = model.num_gaussians
    prov = torch.zeros(n, dtype=torch.int64)
    prov[torch.arange(n) % 3 == 1] = 1
    prov[torch.arange(n) % 6 == 2] = 2
    model.provenance = prov
    return trainer, out


class TestData:
    def test_splat_covariances_match_scipy(self):
        gen = torch.Generator().manual_seed(0)
        q = torch.randn(50, 4, generator=gen, dtype=torch.float64)
        log_s = torch.randn(50, 3, generator=gen, dtype=torch.float64) * 0.5
        a = splat_arrays(torch.zeros(50, 3), q, log_s, torch.zeros(50), torch.zeros(50, 1, 3))
        rot = Rotation.from_quat(q[:, [1, 2, 3, 0]].numpy()).as_matrix()  # scipy: xyzw
        s2 = np.exp(2 * log_s.numpy())
        ref = np.einsum("nij,nj,nkj->nik", rot, s2, rot)
        np.testing.assert_allclose(a["covariances"], ref, rtol=1e-4, atol=1e-6)
        assert a["centers"].dtype == np.float32 and a["opacities"].shape == (50, 1)

    def test_colours_and_opacity(self):
        rgb = torch.tensor([[0.1, 0.7, 0.3]])
        a = splat_arrays(torch.zeros(1, 3), torch.tensor([[1.0, 0, 0, 0]]), torch.zeros(1, 3),
                         torch.tensor([math.log(0.8 / 0.2)]), rgb_to_sh(rgb)[:, None])  # fmt: skip
        np.testing.assert_allclose(a["rgbs"], rgb.numpy(), atol=1e-6)
        np.testing.assert_allclose(a["opacities"], [[0.8]], atol=1e-6)

    def test_groups_partition_the_model_by_node_and_provenance(self, run):
        model = run[0].model
        groups = viewer_groups(model, max_gaussians=None)
        rows = torch.cat([g.rows for g in groups])
        assert sorted(rows.tolist()) == list(range(model.num_gaussians))
        for g in groups:
            assert bool((model.node_ids[g.rows] == g.node).all())
            assert bool(((model.provenance[g.rows] > 0) == g.added).all())
            np.testing.assert_allclose(g.arrays["centers"], model.params["means"][g.rows].detach().numpy())
        added = sum(int(g.rows.numel()) for g in groups if g.added)
        assert added == int((model.provenance > 0).sum()) > 0
        assert {g.node for g in groups} == set(range(-1, len(model.track_ids)))

    def test_subset(self, run):
        model = run[0].model
        groups = viewer_groups(model, max_gaussians=500, seed=3)
        rows = torch.cat([g.rows for g in groups])
        assert rows.numel() == 500 and rows.unique().numel() == 500
        with pytest.raises(ValueError, match="max_gaussians: expected >= 1 or None, got 0"):
            viewer_groups(model, max_gaussians=0)

    def test_node_pose_reproduces_object_to_world(self, run):
        model = run[0].model
        for node in range(len(model.track_ids)):
            for frame in (0, 5):
                wxyz, pos, visible = node_pose(model, node, frame)
                o2w = model.object_to_world[node, frame].double().numpy()
                rot = Rotation.from_quat(np.r_[wxyz[1:], wxyz[0]]).as_matrix()
                np.testing.assert_allclose(rot, o2w[:3, :3], atol=1e-6)
                np.testing.assert_allclose(pos, o2w[:3, 3], atol=1e-9)
                assert visible == bool(model.track_valid[node, frame])
        wxyz, pos, visible = node_pose(model, -1, 3)
        assert wxyz.tolist() == [1, 0, 0, 0] and pos.tolist() == [0, 0, 0] and visible

    def test_frusta_are_the_frame_cameras(self, tiny_scene):
        frusta = frame_frusta(tiny_scene, 2)
        assert [f.view for f in frusta] == list(tiny_scene.frames[2].view_ids)
        for f in frusta:
            info = tiny_scene.views[f.view]
            c2w = info.cam_to_world.double().numpy()
            np.testing.assert_allclose(f.position, c2w[:3, 3], atol=1e-9)
            rot = Rotation.from_quat(np.r_[f.wxyz[1:], f.wxyz[0]]).as_matrix()
            np.testing.assert_allclose(rot, c2w[:3, :3], atol=1e-6)
            cam = tiny_scene.cameras_info[info.camera]
            h, w = cam.image_size
            assert f.fov == pytest.approx(2 * math.atan(h / 2 / float(cam.K[1, 1])))
            assert f.aspect == pytest.approx(w / h)

    def test_frusta_of_a_rig_of_two_sizes(self, tmp_path):
        from tests.data.multisize_sample import write_multisize_sample
        from vadgs.data import load_scene

        sc = load_scene(write_multisize_sample(tmp_path))
        frusta = frame_frusta(sc, 0)
        by_size = {sc.image_size(f.view): f for f in frusta}
        assert set(by_size) == {(120, 200), (144, 240)}
        for (h, w), f in by_size.items():  # each frustum at its own view's size and focal length
            fy = float(sc.cameras_info[f.camera].K[1, 1])
            assert f.aspect == pytest.approx(w / h) and f.fov == pytest.approx(2 * math.atan(h / 2 / fy))


@pytest.fixture
def server():
    s = viser.ViserServer(host="127.0.0.1", port=_free_port(), verbose=False)
    yield s
    s.stop()


class TestViserScene:
    def test_frame_slider_poses_the_cars(self, run, tiny_scene, server):
        model = run[0].model
        viewer = build_viewer(model, tiny_scene, server, frame=1, max_gaussians=None)
        assert viewer.slider.value == 1 and viewer.choice.value == FILTERS[0]
        for frame in (1, 6):
            viewer.set_frame(frame)
            for g, h in zip(viewer.groups, viewer.handles):
                if g.node < 0:
                    np.testing.assert_allclose(h.position, 0.0)
                    continue
                o2w = model.object_to_world[g.node, frame].double().numpy()
                np.testing.assert_allclose(h.position, o2w[:3, 3], atol=1e-6)
                assert h.visible == bool(model.track_valid[g.node, frame])
            assert len(viewer.frusta) == len(tiny_scene.frames[frame].view_ids)
            assert viewer.slider.value == frame
            assert viewer.index.content == f"frame index {tiny_scene.frames[frame].index}"
        with pytest.raises(ValueError, match=r"frame: expected a position in \[0, 8\), got 8"):
            viewer.set_frame(8)

    def test_vad_filter(self, run, tiny_scene, server):
        model = run[0].model
        viewer = build_viewer(model, tiny_scene, server, max_gaussians=None)
        total = model.num_gaussians
        added = int((model.provenance > 0).sum())

        def shown() -> int:
            return sum(viewer.visible_counts().values())

        valid_tracks = model.track_valid[:, 0]
        hidden = sum(
            int((model.node_ids == k).sum()) for k in range(len(model.track_ids)) if not valid_tracks[k]
        )
        assert shown() == total - hidden
        viewer.set_filter(FILTERS[1])
        assert 0 < shown() <= added
        assert all(
            h.visible == (g.added and viewer.visible(g)) for g, h in zip(viewer.groups, viewer.handles)
        )
        viewer.set_filter(FILTERS[2])
        assert all(not h.visible for g, h in zip(viewer.groups, viewer.handles) if g.added)
        with pytest.raises(ValueError, match="filter: expected one of"):
            viewer.set_filter("some")

    def test_frames_must_match(self, run, tiny_scene, server):
        model = run[0].model
        model2 = type(model).from_state(model.state_dict(), model.extra_state())
        model2.object_to_world = model2.object_to_world[:, :3]
        with pytest.raises(ValueError, match=r"model has 3 frames, scene .* 8"):
            build_viewer(model2, tiny_scene, server)


def test_cli_frame_outside_the_scene(run, capsys):
    from vadgs.cli import main

    trainer, out = run
    indices = [f.index for f in trainer.scene.frames]
    for command in ("view", "export"):
        assert main([command, str(out), "--frame", "99"]) == 2
        err = capsys.readouterr().err
        assert f"--frame: scene {trainer.scene.name!r} has frames {indices[0]}..{indices[-1]}, got 99" in err


def _screenshot(url: str, path, ready) -> tuple[float, float]:
    """Screenshot until ``ready(fractions)``: on a busy machine the page may draw after the budget."""
    for budget in (30000, 60000, 120000):
        browser_screenshot(url, path, size=(1000, 700), budget_ms=budget, chromium=CHROMIUM)
        fractions = _colour_fractions(path)
        if ready(fractions):
            break
    return fractions


def _colour_fractions(png) -> tuple[float, float]:
    """Fractions of green and magenta pixels in the 3D area (the GUI panel and notices cut away)."""
    import imageio.v3 as iio

    img = iio.imread(png)[..., :3].astype(int)[250:650, 100:700]
    r, g, b = img[..., 0], img[..., 1], img[..., 2]
    green = (g > 120) & (r < 90) & (b < 90)
    magenta = (r > 120) & (b > 120) & (g < 90)
    return float(green.mean()), float(magenta.mean())


@needs_chromium
class TestBrowser:
    """Headless Chromium (Debian's package, software WebGL) loads the page and draws the Gaussians."""

    def test_screenshot_shows_the_gaussians_and_the_filter_hides_additions(
        self, run, tiny_scene, server, tmp_path
    ):
        model = type(run[0].model).from_state(run[0].model.state_dict(), run[0].model.extra_state())
        added = model.provenance > 0
        with torch.no_grad():  # initial Gaussians green, VAD-GS additions magenta, all opaque
            rgb = torch.where(added[:, None], torch.tensor([1.0, 0.0, 1.0]), torch.tensor([0.0, 1.0, 0.0]))
            model.params["sh_dc"][:, 0] = rgb_to_sh(rgb)
            model.params["opacity_logits"].fill_(4.0)
        viewer = build_viewer(model, tiny_scene, server, max_gaussians=None)
        url = f"http://127.0.0.1:{server.get_port()}"
        green, magenta = _screenshot(url, tmp_path / "all.png", lambda f: f[0] > 0.05 and f[1] > 0.02)
        assert green > 0.05 and magenta > 0.02, (green, magenta)
        viewer.set_filter(FILTERS[2])
        assert viewer.choice.value == FILTERS[2]
        green2, magenta2 = _screenshot(url, tmp_path / "without.png", lambda f: f[0] > 0.05)
        assert green2 > 0.05 and magenta2 < 0.002, (green2, magenta2)

    def test_vadgs_view_serves_the_gui(self, run, tmp_path):
        trainer, out = run
        port = _free_port()
        proc = subprocess.Popen(
            [sys.executable, "-m", "vadgs.cli", "--threads", "1", "view", str(out), "--host", "127.0.0.1",
             "--port", str(port), "--frame", str(trainer.scene.frames[2].index), "--timeout", "120"],
            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
        )  # fmt: skip
        try:
            lines = []
            t0 = time.monotonic()
            while time.monotonic() - t0 < 60:
                line = proc.stdout.readline()
                lines.append(line)
                if line.startswith("open http") or not line:
                    break
            assert lines[-1].startswith(f"open http://127.0.0.1:{port}"), "".join(lines)
            cmd = [CHROMIUM, "--headless=new", "--no-sandbox", "--virtual-time-budget=20000", "--dump-dom"]
            dom = subprocess.run(
                [*cmd, f"http://127.0.0.1:{port}"], capture_output=True, text=True, timeout=120
            ).stdout
        finally:
            proc.terminate()
            proc.wait(30)
        assert f"{trainer.model.num_gaussians} Gaussians" in dom
        assert f"frame index {trainer.scene.frames[2].index}" in dom
        assert "VAD-GS additions" in dom
