"""VAD-GS in a plain, gsplat-style training loop — no ``vadgs.train.Trainer``.

What a gsplat ``simple_trainer`` user keeps: parameters in a ``ParameterDict`` with gsplat's names
(``means``, ``scales`` (log), ``quats``, ``opacities`` (logits), ``sh0``, ``shN``), one Adam per
parameter in a dict, their own render call and their own loss. What they add: a
:class:`~vadgs.train.vad.VisibilityAwareDensification` strategy (a dataclass, called like gsplat's
``DefaultStrategy``: ``check_sanity`` / ``initialize_state`` / ``step_pre_backward`` /
``step_post_backward``), the data it reads as a :class:`~vadgs.train.vad.inputs.VisibilityInputs`
(cameras, image loader, LiDAR or TRACK observations; the loop below sees only that, no vadgs
``Scene``), a :class:`~vadgs.train.vad.StrategyContext` that tells it how to render a view, and the
geometric losses on its priors through :func:`vadgs.train.losses.geometric_losses`, weighted and
scheduled by a :class:`~vadgs.train.losses.GeometricLossConfig` (the paper's weights; the hard term
every 4th step, at every pixel).

Rendering: :func:`vadgs.render.rasterize_gaussians` (pure torch, CPU or GPU) by default;
:func:`vadgs.render.gsplat_backend.rasterize_gaussians_gsplat` (gsplat's CUDA ``rasterization``,
same conventions and outputs) with ``--backend gsplat``, the default when CUDA and gsplat are
available. The CUDA path has not run here (no GPU); its conventions are checked on the CPU
against gsplat's pure-torch reference (``tests/render/test_gsplat_backend.py``).

Run (the bundled sample, static Gaussians from its LiDAR; moving cars are left to the background):

    python examples/gsplat_loop_vad.py --steps 300 --out outputs/gsplat_loop
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import torch

from vadgs.data import Scene, load_scene, sample_scene_path
from vadgs.data.lidar import accumulate_lidar
from vadgs.geometry import invert_rigid
from vadgs.render import rasterize_gaussians, rgb_to_sh
from vadgs.render.gsplat_backend import rasterize_gaussians_gsplat
from vadgs.train import losses as L
from vadgs.train.strategy import DefaultStrategy, DefaultStrategyConfig
from vadgs.train.vad import StrategyContext, ViewRender, VisibilityAwareDensification, VisibilityDensifyConfig
from vadgs.train.vad.inputs import VisibilityInputs

BACKGROUND = 0.7  # a grey sky behind the Gaussians


def make_params(points: torch.Tensor, colors: torch.Tensor, spacing: torch.Tensor, sh_degree: int = 1):
    """gsplat-style parameters: isotropic Gaussians of size ``spacing`` at the points, opacity 0.5."""
    n = points.shape[0]
    quats = torch.zeros(n, 4, device=points.device)
    quats[:, 0] = 1.0
    k = (sh_degree + 1) ** 2
    return torch.nn.ParameterDict(
        {
            "means": torch.nn.Parameter(points.clone()),
            "scales": torch.nn.Parameter(torch.log(spacing.clamp(min=1e-3))[:, None].repeat(1, 3)),
            "quats": torch.nn.Parameter(quats),
            "opacities": torch.nn.Parameter(torch.zeros(n, device=points.device)),
            "sh0": torch.nn.Parameter(rgb_to_sh(colors)[:, None, :].clone()),
            "shN": torch.nn.Parameter(torch.zeros(n, k - 1, 3, device=points.device)),
        }
    )


def make_optimizers(params: torch.nn.ParameterDict, scene_scale: float) -> dict[str, torch.optim.Adam]:
    """One Adam per parameter (gsplat's convention), 3DGS learning rates."""
    lrs = {"means": 1.6e-4 * scene_scale, "scales": 5e-3, "quats": 1e-3, "opacities": 5e-2, "sh0": 2.5e-3}
    lrs["shN"] = lrs["sh0"] / 20
    return {k: torch.optim.Adam([params[k]], lr=lr, eps=1e-15) for k, lr in lrs.items()}


def render(
    params,
    inputs: VisibilityInputs,
    view: int,
    backend: str = "torch",
    opacity_override=None,
    stride: int = 1,
):
    """Render one view: ``(color (1, 3, H, W), depth, alpha (1, 1, H, W), normals (1, 3, H, W), info)``.

    ``info`` is gsplat's (``means2d``, ``radii``, ``width``, ``height``, ``n_cameras``) for the base
    strategy. ``backend="gsplat"``: gsplat's rasterizer (CUDA tensors: its CUDA kernels). ``stride``
    s: every s-th pixel row and column only (``(ceil(H / s), ceil(W / s))``: the hard depth at
    ``GeometricLossConfig.hard_stride``).
    """
    dev = params["means"].device
    w2c = inputs.cameras.world_to_cam[view : view + 1].to(dev)
    K = inputs.cameras.K[view : view + 1].to(dev)
    h, w = inputs.size(view)
    if stride > 1:
        K = K.clone()
        K[:, :2] /= stride
        h, w = -(-h // stride), -(-w // stride)
    opac = torch.sigmoid(params["opacities"])
    if opacity_override is not None:
        opac = torch.full_like(opac.detach(), opacity_override)
    sh = torch.cat([params["sh0"], params["shN"]], 1)
    degree = math.isqrt(sh.shape[1]) - 1
    bg = torch.full((3,), BACKGROUND, device=dev)
    raster = rasterize_gaussians_gsplat if backend == "gsplat" else rasterize_gaussians
    out = raster(
        params["means"], params["quats"], torch.exp(params["scales"]), opac, sh, w2c, K, (h, w),
        background=bg, sh_degree=degree,
    )  # fmt: skip
    info = {"means2d": out.means2d, "radii": out.radii, "width": w, "height": h, "n_cameras": 1}
    return out.color, out.depth, out.alpha, out.normals, info


def lidar_init(scene: Scene, max_points: int = 20000, seed: int = 0):
    """Points, colours (from the first view that sees each) and spacings from the scene's static LiDAR."""
    acc = accumulate_lidar(scene)
    g = torch.Generator().manual_seed(seed)
    pts = acc.points[torch.randperm(acc.points.shape[0], generator=g)[:max_points]]
    colors = torch.full_like(pts, 0.5)
    for v in scene.train_views:  # colour each point from a view that sees it
        cams = scene.cameras([v])
        img = scene.load_images([v])[0]
        c = pts @ cams.world_to_cam[0, :3, :3].T + cams.world_to_cam[0, :3, 3]
        uv = c[:, :2] / c[:, 2:].clamp(min=1e-6) @ cams.K[0, :2, :2].T + cams.K[0, :2, 2]
        u, vv = uv[:, 0].round().long(), uv[:, 1].round().long()
        h, w = cams.image_size
        ok = (c[:, 2] > 0.1) & (u >= 0) & (u < w) & (vv >= 0) & (vv < h)
        colors[ok] = img[:, vv[ok], u[ok]].T
    d = torch.cdist(pts, pts).topk(4, largest=False).values[:, 1:].mean(1)
    return pts, colors, d


def scene_scale(inputs: VisibilityInputs) -> float:
    """Radius of the training cameras' centres (3DGS's normalisation), times 1.1."""
    c = invert_rigid(inputs.cameras.world_to_cam[list(inputs.train_views)])[:, :3, 3]
    return float((c - c.mean(0)).norm(dim=-1).max() * 1.1)


def train(
    inputs: VisibilityInputs,
    params: torch.nn.ParameterDict,
    steps: int,
    vad: VisibilityDensifyConfig | None = None,
    adc: DefaultStrategyConfig | None = None,
    backend: str = "torch",
    seed: int = 0,
    geometry: L.GeometricLossConfig | None = None,
    callback=None,
):
    """The loop, on the inputs only. Returns ``(params, optimizers, strategy, state)``.

    ``geometry``: the geometric losses' weights and schedule (default: the paper's weights, the hard
    term every 4th step at every pixel); ``hard_fused`` is vadgs's trainer's, not used here.
    """
    geometry = geometry or L.GeometricLossConfig(hard_every=4, hard_stride=1)
    views = list(inputs.train_views)
    scale = scene_scale(inputs)
    optimizers = make_optimizers(params, scale)
    generator = torch.Generator().manual_seed(seed + 1)

    @torch.no_grad()
    def render_for_strategy(view: int) -> ViewRender:
        _, depth, alpha, normals, _ = render(params, inputs, view, backend)
        return ViewRender(depth[0], alpha[0], normals[0])

    context = StrategyContext(
        render_for_strategy, total_steps=steps, steps_per_cycle=len(views), generator=generator
    )
    base = DefaultStrategy(
        adc or DefaultStrategyConfig(refine_start_iter=100, refine_every=50, reset_every=0)
    )
    strategy = VisibilityAwareDensification.from_config(vad, base=base)
    strategy.check_sanity(params, optimizers)
    strategy.prepare(inputs, context)  # the visibility index, once
    state = strategy.initialize_state(scene_scale=scale)
    sampler = torch.Generator().manual_seed(seed)
    order: list[int] = []
    images: dict[int, torch.Tensor] = {}
    for step in range(steps):
        if not order:  # views sampled without replacement, one cycle after the other
            order = [views[i] for i in torch.randperm(len(views), generator=sampler).tolist()]
        view = order.pop(0)
        if view not in images:
            images[view] = inputs.load_image(view, None)[None].to(params["means"].device)
        color, depth, _, normals, info = render(params, inputs, view, backend)
        strategy.step_pre_backward(params, optimizers, state, step, info)
        loss = L.color_loss(color, images[view])
        targets = strategy.geometry_targets(state, view)  # VAD-GS's MVS / voxel depth priors
        if targets is not None:
            weights = geometry.weights(step, steps)
            hard = None
            if targets.depth is not None and geometry.hard_applies(step, steps):
                hard = render(params, inputs, view, backend, 1.0, geometry.hard_stride)[1]
            terms = L.geometric_losses(
                targets.to(depth.device), depth, normals, weights, hard, geometry.hard_stride
            )
            loss = loss + sum(terms.values())
        loss.backward()
        for opt in optimizers.values():
            opt.step()
            opt.zero_grad(set_to_none=True)
        strategy.step_post_backward(params, optimizers, state, step, info)
        for event in state.pop("pending_log", []):
            print(f"step {step}: {event['summary']}")
        if callback is not None:
            callback(step, float(loss.detach()))
    return params, optimizers, strategy, state


@torch.no_grad()
def test_psnr(scene: Scene, params, backend: str = "torch") -> float:
    """Mean PSNR over the test views (moving cars included)."""
    inputs = VisibilityInputs.from_scene(scene)
    out = []
    for v in scene.test_views:
        color = render(params, inputs, v, backend)[0].clamp(0, 1)
        mse = torch.mean((color - scene.load_images([v]).to(color.device)) ** 2)
        out.append(float(-10 * torch.log10(mse)))
    return sum(out) / len(out)


def main() -> None:
    """Command line."""
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--steps", type=int, default=300)
    ap.add_argument("--scale", type=float, default=0.5)
    ap.add_argument(
        "--backend", choices=["torch", "gsplat"], default=None, help="default: gsplat on CUDA if installed"
    )
    ap.add_argument("--out", default="outputs/gsplat_loop")
    args = ap.parse_args()
    backend = args.backend
    if backend is None:
        try:
            import gsplat  # noqa: F401

            backend = "gsplat" if torch.cuda.is_available() else "torch"
        except ImportError:
            backend = "torch"
    device = "cuda" if backend == "gsplat" else "cpu"
    scene = load_scene(sample_scene_path(), scale=args.scale)
    pts, colors, spacing = lidar_init(scene)
    params = make_params(pts, colors, spacing).to(device)
    vad = VisibilityDensifyConfig(every_cycles=2, max_instances=3)
    inputs = VisibilityInputs.from_scene(scene)  # or VisibilityInputs.from_gsplat_parser(parser)
    params, _, _, state = train(inputs, params, args.steps, vad, backend=backend)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    result = {
        "backend": backend,
        "steps": args.steps,
        "gaussians": int(params["means"].shape[0]),
        "test_psnr": round(test_psnr(scene, params, backend), 2),
        "events": [{k: e[k] for k in ("step", "flagged_instances", "added")} for e in state["vad_events"]],
    }
    (out / "result.json").write_text(json.dumps(result, indent=2))
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
