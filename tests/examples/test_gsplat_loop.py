"""examples/gsplat_loop_vad.py: VAD-GS in a plain gsplat-style loop (ParameterDict with gsplat's
names, one Adam per parameter, no vadgs Trainer) flags a deleted facade and re-populates it."""

import importlib.util
from pathlib import Path

import pytest
import torch

from vadgs.data import load_scene, sample_scene_path
from vadgs.geometry import backproject_depth
from vadgs.train.strategy import DefaultStrategyConfig
from vadgs.train.vad import ReconstructConfig, VisibilityDensifyConfig, VisibilityInputs

BUILDING = 9  # a large facade of the sample with LiDAR on its lower part


def _example():
    path = Path(__file__).resolve().parents[2] / "examples" / "gsplat_loop_vad.py"
    spec = importlib.util.spec_from_file_location("gsplat_loop_vad", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@pytest.fixture(scope="module")
def setup():
    scene = load_scene(sample_scene_path(), scale=0.5)
    views = scene.train_views
    depth = scene.load_depths(views)
    cams = scene.cameras(views)
    step = 3
    pts = backproject_depth(depth, cams.K, cams.cam_to_world)[:, :, ::step, ::step].permute(0, 2, 3, 1)
    img = scene.load_images(views)[:, :, ::step, ::step].permute(0, 2, 3, 1)
    ins = scene.load_instances(views)[:, ::step, ::step]
    spacing = depth[:, 0, ::step, ::step] / cams.K[:, 0, 0, None, None] * step
    valid = (depth[:, 0, ::step, ::step] > 0) & ~torch.isin(ins, torch.tensor(sorted(scene.tracks)))
    return scene, pts[valid], img[valid], ins[valid], spacing[valid]


def test_loop_flags_and_repopulates_a_deleted_facade(setup):
    ex = _example()
    scene, pts, col, ins, spc = setup
    keep = ins != BUILDING
    params = ex.make_params(pts[keep], col[keep], spc[keep], sh_degree=0)
    params["opacities"].data.fill_(3.0)  # opaque: the complete instances pass the test
    assert set(params) == {"means", "scales", "quats", "opacities", "sh0", "shN"}  # gsplat's names
    n0 = params["means"].shape[0]
    vad = VisibilityDensifyConfig(
        every_cycles=1,
        max_instances=1,
        skip_classes=("road", "sidewalk", "tree", "car", "sign"),
        reconstruct=ReconstructConfig(max_crop=96),
    )
    adc = DefaultStrategyConfig(refine_start_iter=10**6)  # only VAD-GS changes the set of Gaussians
    losses = []
    steps = len(scene.train_views) + 2  # the event after the first cycle, then two steps with priors
    params, optimizers, strategy, state = ex.train(
        VisibilityInputs.from_scene(scene),
        params,
        steps,
        vad,
        adc,
        callback=lambda s, loss: losses.append(loss),
    )
    assert len(losses) == steps and all(torch.isfinite(torch.tensor(losses)))
    (event,) = state["vad_events"]
    assert event["step"] == len(scene.train_views) - 1
    done = {e["instance"]: e for e in event["instances"]}
    assert BUILDING in done and done[BUILDING]["added"] > 100
    assert params["means"].shape[0] == n0 + event["added"]
    # the new Gaussians lie on the deleted facade (they trained two more steps)
    new = params["means"][n0:].detach()
    d = torch.cdist(new[::3], pts[~keep]).min(1).values
    # 0.11-0.16 m over PatchMatch seeds 1-6 of both the batched and the per-candidate search
    # (a seed's draws, not the search, set where in that range a run falls); metres off otherwise
    assert float(d.median()) < 0.2
    assert float((d < 0.3).float().mean()) > 0.8
    # every optimizer of the dict follows the new rows; the priors feed the loss
    for name, opt in optimizers.items():
        st = opt.state[params[name]]
        assert st["exp_avg"].shape == params[name].shape, name
    group = done[BUILDING]["views"][0]
    assert strategy.geometry_targets(state, group[0]) is not None
