"""VAD-GS in the loop shape of gsplat's ``examples/simple_trainer.py`` (v1.5.3) with the diff of
``examples/gsplat_simple_trainer.md``, on the CPU.

What runs is what the diff adds to ``simple_trainer.py``: a gsplat ``Parser`` (here the duck-typed
one of :mod:`tests.train.gsplat_parser`, on the bundled COLMAP sample at half resolution),
``splats`` / ``optimizers`` in gsplat's layout (one Adam per key), gsplat's ``DefaultStrategy``
wrapped by :meth:`VisibilityAwareDensification.from_config`, ``check_sanity`` /
``initialize_state`` / ``step_pre_backward`` / ``step_post_backward(..., packed=...)`` with
keyword arguments, a ``Dataset``-like shuffled loader of the training split (every
``test_every``-th image held out), and a ``rasterize_splats`` that returns gsplat's
``(renders [C, H, W, 3|4], alphas [C, H, W, 1], info)`` from gsplat's ``K`` (pixel centres at
``i + 0.5``) — rendered by :func:`vadgs.render.rasterize_gaussians` instead of gsplat's CUDA
``rasterization`` (no GPU here). ``render_for_vad`` is the diff's method, line for line.

The scene: dense Gaussians of the sample's surfaces, opaque, with one derived instance of the COLMAP
path deleted — the 10 m ground cell of buildings 9 and 10
(:data:`~tests.train.gsplat_parser.FACADE_POINT`). After one cycle of the training views, the event
must flag that cell and re-populate it.
"""

from __future__ import annotations

import dataclasses
from types import SimpleNamespace
from typing import Optional

import pytest
import torch

from vadgs.render import rasterize_gaussians
from vadgs.train.vad import (
    ReconstructConfig,
    StrategyContext,
    ViewRender,
    VisibilityAwareDensification,
    VisibilityDensifyConfig,
    VisibilityInputs,
)

from .gsplat_parser import facade_splats

gsplat_strategy = pytest.importorskip("gsplat.strategy")


class Runner:
    """The parts of simple_trainer's ``Runner`` that the diff touches, on the CPU."""

    def __init__(self, parser, vad: VisibilityDensifyConfig, max_steps: int) -> None:
        self.device = "cpu"
        self.cfg = SimpleNamespace(sh_degree=0)  # the splats' shN is of degree 0
        self.parser = parser
        self.trainset = [i for i in range(len(parser.image_names)) if i % parser.test_every != 0]
        self.scene_scale = 1.0
        self.strategy = gsplat_strategy.DefaultStrategy()  # cfg.strategy (refine from step 500)
        inputs = VisibilityInputs.from_gsplat_parser(self.parser)
        self.splats, self.optimizers, self.in_cell = facade_splats(parser, inputs)
        # Densification Strategy: the unchanged lines, then the diff's
        self.strategy.check_sanity(self.splats, self.optimizers)
        self.strategy_state = self.strategy.initialize_state(scene_scale=self.scene_scale)
        self.vad = VisibilityAwareDensification.from_config(vad, base=self.strategy)
        self.vad.check_sanity(self.splats, self.optimizers)
        self.vad.prepare(inputs, StrategyContext(self.render_for_vad, max_steps, len(self.trainset)))
        self.strategy_state = self.vad.initialize_state(scene_scale=self.scene_scale)

    def rasterize_splats(self, camtoworlds, Ks, width, height, render_mode="RGB", sh_degree=None, **kwargs):
        """gsplat's outputs and ``info`` from vadgs's renderer (``K``: gsplat's pixel convention)."""
        if sh_degree is None:  # gsplat's rasterization then takes the SH coefficients as colours
            raise AssertionError("sh_degree is required with [N, K, 3] SH coefficients")
        K = Ks.clone()
        K[:, :2, 2] -= 0.5  # gsplat: pixel centres at i + 0.5; vadgs: at i
        s = self.splats
        out = rasterize_gaussians(
            s["means"], s["quats"], torch.exp(s["scales"]), torch.sigmoid(s["opacities"]),
            torch.cat([s["sh0"], s["shN"]], 1), torch.linalg.inv(camtoworlds), K, (height, width),
        )  # fmt: skip
        renders = out.color.permute(0, 2, 3, 1)
        if render_mode == "RGB+ED":
            renders = torch.cat([renders, out.depth.permute(0, 2, 3, 1)], -1)
        info = {"means2d": out.means2d, "radii": out.radii, "width": width, "height": height}
        info.update(n_cameras=1, gaussian_ids=None)
        return renders, out.alpha.permute(0, 2, 3, 1), info

    @torch.no_grad()
    def render_for_vad(self, view: int) -> ViewRender:
        """VAD-GS's render of a parser view: expected depth and opacity (normals unknown)."""
        cid = self.parser.camera_ids[view]
        c2w = torch.from_numpy(self.parser.camtoworlds[view : view + 1]).float().to(self.device)
        K = torch.from_numpy(self.parser.Ks_dict[cid][None]).float().to(self.device)
        w, h = self.parser.imsize_dict[cid]
        rgbd, alphas, _ = self.rasterize_splats(
            c2w, K, w, h, sh_degree=self.cfg.sh_degree, render_mode="RGB+ED"
        )
        depth, alpha = rgbd[0, ..., 3:].permute(2, 0, 1), alphas[0].permute(2, 0, 1)
        return ViewRender(depth, alpha, torch.zeros_like(rgbd[0, ..., :3]).permute(2, 0, 1))

    def data(self, item: int) -> dict:
        """``Dataset(parser, split="train")[item]``: camtoworld, K, image (0..255), image_id."""
        view = self.trainset[item]
        cid = self.parser.camera_ids[view]
        img = self.vad.inputs.load_image(view, None).permute(1, 2, 0) * 255.0
        return {
            "camtoworld": torch.from_numpy(self.parser.camtoworlds[view]).float()[None],
            "K": torch.from_numpy(self.parser.Ks_dict[cid]).float()[None],
            "image": img[None],
            "image_id": torch.tensor([item]),
        }

    def train(self, max_steps: int, packed: bool = False) -> list[float]:
        """simple_trainer's loop: shuffled epochs of the train split, L1 loss, gsplat's calls."""
        gen = torch.Generator().manual_seed(0)
        order: list[int] = []
        losses = []
        for step in range(max_steps):
            if not order:  # DataLoader(shuffle=True): a new epoch
                order = torch.randperm(len(self.trainset), generator=gen).tolist()
            data = self.data(order.pop(0))
            pixels = data["image"] / 255.0
            height, width = pixels.shape[1:3]
            renders, _, info = self.rasterize_splats(
                data["camtoworld"], data["K"], width, height, sh_degree=0
            )
            (self.vad or self.strategy).step_pre_backward(
                params=self.splats,
                optimizers=self.optimizers,
                state=self.strategy_state,
                step=step,
                info=info,
            )
            loss = torch.nn.functional.l1_loss(renders, pixels)
            loss.backward()
            for optimizer in self.optimizers.values():
                optimizer.step()
                optimizer.zero_grad(set_to_none=True)
            (self.vad or self.strategy).step_post_backward(
                params=self.splats,
                optimizers=self.optimizers,
                state=self.strategy_state,
                step=step,
                info=info,
                packed=packed,
            )
            losses.append(float(loss.detach()))
        return losses


@pytest.fixture(scope="module")
def parser(colmap_sample_parser):
    return colmap_sample_parser


def test_simple_trainer_shape_repopulates_a_deleted_facade(parser):
    vad = VisibilityDensifyConfig(  # the sample's world is street metres: vadgs's lengths (10 m cells)
        every_cycles=1, max_instances=1, time_budget=None, reconstruct=ReconstructConfig(max_crop=64),
        scene_depth=10.0,
    )  # fmt: skip
    cycle = 21  # 24 images, every 8th held out
    steps = cycle + 3  # the event after the first cycle, then three steps with the new Gaussians
    runner = Runner(parser, vad, steps)
    assert len(runner.trainset) == cycle
    n0 = runner.splats["means"].shape[0]
    index = runner.vad.index
    assert index is not None and index.derives_instances  # built by prepare, before the loop
    # the deleted cell is one derived instance of the visibility index
    cells = index.cell_ids()[runner.in_cell(index.covis.voxel_centers)]  # the voxels' world centres
    facade = int(cells.mode().values)
    assert (cells == facade).float().mean() > 0.95  # the deleted cell is (nearly) one derived cell
    losses = runner.train(steps)
    assert all(torch.isfinite(torch.tensor(losses)))
    (event,) = runner.strategy_state["vad_events"]
    assert event["step"] == cycle - 1
    # flagged: the only incomplete instance of an opaque, otherwise complete model
    assert event["flagged_instances"] >= 1 and event["instances"][0]["instance"] == facade
    assert event["instances"][0]["class"] == "static" and event["instances"][0]["reason"] == "ok"
    new = runner.splats["means"][n0:].detach()
    assert new.shape[0] == event["added"]
    inside = int(runner.in_cell(new).sum())
    assert inside > 300, f"{inside} of {new.shape[0]} new Gaussians inside the deleted cell"
    assert inside > 0.8 * new.shape[0]
    # gsplat's optimizers and the base's running statistics follow the new rows
    n = runner.splats["means"].shape[0]
    for name, opt in runner.optimizers.items():
        st = opt.state[runner.splats[name]]
        assert st["exp_avg"].shape == runner.splats[name].shape, name
    assert runner.strategy_state["grad2d"].shape == (n,) and runner.strategy_state["count"].shape == (n,)
    assert float(runner.strategy_state["count"][n0:].sum()) > 0  # the new rows are seen after the event
    # the events reach the loop through the state, bounded
    assert len(runner.strategy_state["pending_log"]) == 1 <= runner.vad.log_size


def test_the_documented_diff_is_this_loop():
    """examples/gsplat_simple_trainer.md: its diff is the .diff file, at most 40 changed lines, and
    the lines it adds for the strategy are the ones this test's Runner runs."""
    import inspect
    from pathlib import Path

    examples = Path(__file__).resolve().parents[2] / "examples"
    doc = (examples / "gsplat_simple_trainer.md").read_text()
    block = doc.split("```diff\n", 1)[1].rsplit("```", 1)[0]
    assert block == (examples / "gsplat_simple_trainer.diff").read_text()
    added = [ln[1:] for ln in block.splitlines() if ln.startswith("+") and not ln.startswith("+++")]
    removed = [ln[1:] for ln in block.splitlines() if ln.startswith("-") and not ln.startswith("---")]
    assert len(added) + len(removed) <= 40
    assert block in (examples.parent / "docs" / "vad.md").read_text()  # shown there too
    source = inspect.getsource(Runner)
    body = [ln.strip() for ln in added if ln.strip()]
    start = body.index("def render_for_vad(self, view: int) -> ViewRender:")
    for line in body[start : start + 10]:  # render_for_vad, line for line
        assert line in source, line
    for call in ("VisibilityAwareDensification.from_config(", ".check_sanity(self.splats, self.optimizers)"):
        assert any(call in ln for ln in body) and call in source
    assert sum("(self.vad or self.cfg.strategy).step_" in ln for ln in added) == 3


@dataclasses.dataclass
class _SimpleTrainerConfig:  # the fields of simple_trainer's Config that matter here
    max_steps: int = 30_000
    steps_scaler: float = 1.0
    vad: Optional[VisibilityDensifyConfig] = None  # noqa: UP045 (the diff's spelling)


def test_tyro_spells_the_vad_entry_of_the_diff(monkeypatch):
    """simple_trainer's command line: ``tyro.extras.overridable_config_cli`` over ``configs``."""
    tyro = pytest.importorskip("tyro")
    cfg = _SimpleTrainerConfig
    configs = {  # as in the diff: default, mcmc, and the new vad entry
        "default": ("gsplat's default strategy", cfg()),
        "mcmc": ("MCMC", cfg(max_steps=10)),
        "vad": ("VAD-GS around the default strategy", cfg(vad=VisibilityDensifyConfig())),
    }

    def run(*args):
        monkeypatch.setattr("sys.argv", ["simple_trainer.py", *args])
        return tyro.extras.overridable_config_cli(configs)

    assert run("default").vad is None and run("mcmc", "--steps_scaler", "0.25").steps_scaler == 0.25
    assert run("vad").vad == VisibilityDensifyConfig()
    on = run("vad", "--vad.references", "4", "--vad.reconstruct.max-crop", "128", "--vad.time-budget", "None")
    assert (on.vad.references, on.vad.reconstruct.max_crop, on.vad.time_budget) == (4, 128, None)
    assert run("vad", "--vad.skip-classes", "road", "sky").vad.skip_classes == ("road", "sky")
    with pytest.raises(SystemExit):  # tyro prints the error and exits
        run("vad", "--vad.references", "many")
    with pytest.raises(SystemExit):  # no VAD-GS flags on the default entry: its vad is None
        run("default", "--vad.references", "4")
