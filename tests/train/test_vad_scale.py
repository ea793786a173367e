"""VAD-GS at any scene scale: the same scene at scale 1, at scale 1/20, and through gsplat's own
Parser normalisation (and turned and shifted) gives the same voxels, the same flagged instances and
as many new Gaussians.

The scene is the COLMAP sample seen through the Parser-like namespace of
:mod:`tests.train.gsplat_parser` (half resolution), with dense Gaussians of its surfaces and one
10 m ground cell deleted (:func:`~tests.train.gsplat_parser.facade_splats`); one event runs on it.
VAD-GS is given no length: its lengths follow the inputs' median view depth
(``VisibilityInputs.scene_depth``), 11.3 m here, 0.56 at 1/20, and 0.80 in gsplat's
normalised world (gsplat's ``scene_scale``, the cameras' spread, is 0.38 there).
"""

from __future__ import annotations

import copy
import math

import numpy as np
import pytest
import torch

from vadgs.geometry.rotation import quat_multiply, rotation_to_quat
from vadgs.render import RasterConfig, rasterize_gaussians
from vadgs.train.strategy import DefaultStrategy
from vadgs.train.vad import (
    ReconstructConfig,
    StrategyContext,
    ViewRender,
    VisibilityAwareDensification,
    VisibilityInputs,
)

from .gsplat_parser import facade_splats


@pytest.fixture(scope="module")
def project(colmap_sample):
    return colmap_sample


@pytest.fixture(scope="module")
def parser(colmap_sample_parser):
    return colmap_sample_parser


def _transformed(parser, transform: np.ndarray):
    """The parser in another world frame: ``x' = T x`` (``T`` a 4x4 similarity), as gsplat normalises."""
    out = copy.copy(parser)
    out.camtoworlds = transform @ parser.camtoworlds
    scale = np.linalg.norm(transform[:3, 0])
    out.camtoworlds[:, :3, :3] /= scale  # a rotation again
    out.points = (parser.points @ transform[:3, :3].T + transform[:3, 3]).astype(np.float32)
    return out


def _event(parser, transform: np.ndarray, moved=None):
    """One VAD-GS event on the facade scene in the frame ``transform`` (4x4 similarity); ``moved``:
    the parser in that frame (default: ``parser`` transformed).

    Returns:
        ``(strategy, event, in_cell, state)``: ``in_cell`` the share of the new Gaussians that lie, back in
        the sample's frame, in the deleted cell.
    """
    inputs0 = VisibilityInputs.from_gsplat_parser(parser)
    splats, optimizers, in_cell = facade_splats(parser, inputs0)
    n0 = len(splats["means"])
    t = torch.as_tensor(transform, dtype=torch.float32)
    scale = float(t[:3, 0].norm())
    with torch.no_grad():  # the Gaussians turn with the world (their normal: an axis of their rotation)
        splats["means"].copy_(splats["means"] @ t[:3, :3].T + t[:3, 3])
        splats["scales"].add_(math.log(scale))
        turn = rotation_to_quat((t[:3, :3] / scale)[None])[0]
        splats["quats"].copy_(quat_multiply(turn.expand_as(splats["quats"]), splats["quats"]))
    moved = moved if moved is not None else _transformed(parser, transform)
    inputs = VisibilityInputs.from_gsplat_parser(moved)
    raster = RasterConfig(near=0.01 * scale)

    @torch.no_grad()
    def render(view: int) -> ViewRender:
        s = splats
        out = rasterize_gaussians(
            s["means"], s["quats"], s["scales"].exp(), s["opacities"].sigmoid(),
            torch.cat([s["sh0"], s["shN"]], 1), inputs.cameras.world_to_cam[view : view + 1],
            inputs.cameras.K[view : view + 1], inputs.size(view), config=raster,
        )  # fmt: skip
        return ViewRender(out.depth[0], out.alpha[0], out.normals[0])

    vad = VisibilityAwareDensification(
        base=DefaultStrategy(),
        max_instances=1,
        time_budget=None,
        reconstruct=ReconstructConfig(max_crop=64),
    )
    gen = torch.Generator().manual_seed(0)
    vad.prepare(inputs, StrategyContext(render, total_steps=100, steps_per_cycle=21, generator=gen))
    state = vad.initialize_state()
    event = vad.densify(splats, optimizers, state, step=20)
    new = (splats["means"][n0:].detach() - t[:3, 3]) @ torch.linalg.inv(t[:3, :3]).T
    return vad, event, float(in_cell(new).float().mean()) if len(new) else 0.0, state


def _similarity(scale: float, angle: float = 0.0, shift=(0.0, 0.0, 0.0)) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    out = np.eye(4)
    out[:3, :3] = scale * np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
    out[:3, 3] = shift
    return out


@pytest.fixture(scope="module")
def at_scale_1(parser):
    return _event(parser, np.eye(4))


def test_same_event_at_scale_1_and_1_20(parser, at_scale_1):
    a_vad, a, a_in, _ = at_scale_1
    b_vad, b, b_in, _ = _event(parser, _similarity(1 / 20))
    assert a_vad.lengths["scene_depth"] == pytest.approx(11.27, abs=0.01)
    assert b_vad.lengths["scene_depth"] == pytest.approx(a_vad.lengths["scene_depth"] / 20, rel=1e-4)
    assert b_vad.lengths["voxel_size"] == pytest.approx(a_vad.lengths["voxel_size"] / 20, rel=1e-4)
    assert b_vad.lengths["cell_size"] == pytest.approx(a_vad.lengths["cell_size"] / 20, rel=1e-4)
    va, vb = len(a_vad.index.grid), len(b_vad.index.grid)
    assert va > 500 and abs(va - vb) <= 0.02 * va, (va, vb)
    assert a["flagged_instances"] == b["flagged_instances"] >= 1
    assert [i["instance"] for i in a["instances"]] == [i["instance"] for i in b["instances"]]
    assert a["added"] > 200 and abs(a["added"] - b["added"]) <= 0.05 * a["added"], (a["added"], b["added"])
    assert a_in > 0.75 and b_in > 0.75, (a_in, b_in)  # in the deleted facade (measured 0.79: the
    # rest on its border, in the pixels the instance map grows beyond its voxels)


def test_through_gsplats_parser_normalisation(project, parser, at_scale_1, monkeypatch):
    """gsplat's own ``Parser(normalize=True)`` (``../shared``'s v1.5.3 examples; the forked
    ``SceneManager`` over pycolmap 4.x): its world is tilted (PCA-aligned), centred and about 1/14
    of the sample's. The static voxels and the derived cells lie in the scene's own ground frame
    (:func:`~vadgs.geometry.ground.ground_frame`), so the same instance is flagged and repaired
    from the same references and supports. Measured: 744 voxels against 746 (float32 rounding in
    the tilted world moves points across voxel borders); new Gaussians 427, all in the deleted
    cell, against 620 of which 488 in it: the sample's own frame lets the second reference's
    PatchMatch keep ~130 points off the facade (its points spread 19 m across it, against 0.5 m
    here), which the thinning counts as new cells. Before the ground frame: 192 against 287."""
    import sys

    from .gsplat_simple_trainer import GSPLAT_EXAMPLES, SceneManager, prepare_data

    if not GSPLAT_EXAMPLES.is_dir():
        pytest.skip("needs ../shared/third_party/gsplat-v1.5.3")
    pycolmap = pytest.importorskip("pycolmap")
    pytest.importorskip("cv2")
    monkeypatch.setattr(pycolmap, "SceneManager", SceneManager, raising=False)
    monkeypatch.syspath_prepend(str(GSPLAT_EXAMPLES))
    monkeypatch.delitem(sys.modules, "datasets", raising=False)
    monkeypatch.delitem(sys.modules, "datasets.colmap", raising=False)
    from datasets.colmap import Parser

    prepare_data(project, 2)
    gs = Parser(str(project), factor=2, normalize=True, test_every=8)
    assert gs.scene_scale == pytest.approx(0.378, abs=0.001)  # gsplat's scene_scale: not a depth
    a_vad, a, _, _ = at_scale_1
    vad, ev, inside, _ = _event(parser, gs.transform, gs)
    scale = float(np.linalg.norm(gs.transform[:3, 0]))
    assert vad.lengths["scene_depth"] == pytest.approx(a_vad.lengths["scene_depth"] * scale, rel=0.01)
    va, vb = len(a_vad.index.grid), len(vad.index.grid)
    assert abs(va - vb) <= 0.02 * va, (va, vb)
    assert ev["flagged_instances"] == a["flagged_instances"] >= 1
    assert [i["references"] for i in ev["instances"]] == [i["references"] for i in a["instances"]]
    assert [i["views"] for i in ev["instances"]] == [i["views"] for i in a["instances"]]
    assert 0.6 * a["added"] <= ev["added"] <= 1.1 * a["added"], (ev["added"], a["added"])
    assert inside > 0.75, inside  # back in the sample's frame: in the deleted facade
    in_a, in_b = a["added"] * at_scale_1[2], ev["added"] * inside  # new Gaussians in the facade
    assert abs(in_b - in_a) <= 0.2 * in_a, (in_b, in_a)


def test_same_event_turned_shifted_and_scaled(parser, at_scale_1):
    """A turned (0.7 rad about the up), shifted and 1/20 copy: the voxels, cells, flagged instances,
    references and supports are the same, and the new Gaussians as many: measured 636 against 620
    (635 at 1/20 unturned: the rest is float rounding in PatchMatch)."""
    a_vad, a, _, _ = at_scale_1
    vad, ev, inside, _ = _event(parser, _similarity(1 / 20, 0.7, (3.0, -2.0, 1.0)))
    assert len(a_vad.index.grid) == len(vad.index.grid)
    assert torch.equal(vad.index.cell_ids(), a_vad.index.cell_ids())
    assert ev["flagged_instances"] == a["flagged_instances"] >= 1
    assert [i["references"] for i in ev["instances"]] == [i["references"] for i in a["instances"]]
    assert [i["views"] for i in ev["instances"]] == [i["views"] for i in a["instances"]]
    assert abs(ev["added"] - a["added"]) <= 0.05 * a["added"], (ev["added"], a["added"])
    assert inside > 0.75, inside


def test_priors_on_the_voxels_of_an_sfm_scene(at_scale_1):
    """A COLMAP scene's voxels are its sparse SfM points: the MVS priors are kept on them too
    (``mvs_prior_beyond_voxels`` applies on scenes with LiDAR only)."""
    vad, _, _, state = at_scale_1
    assert vad.config.mvs_prior_beyond_voxels and vad.index.inputs.lidar is None  # the default, SfM
    on_voxels = sum(
        int(((d > 0) & (vad.index.voxel_depth(v)[0].to(d.device) > 0)).sum())
        for v, (d, _) in state["vad_priors"].items()
    )
    assert on_voxels > 50, on_voxels
