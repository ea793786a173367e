"""The gsplat backend against vadgs's pure-torch renderer, on the CPU (gsplat's pure-torch reference
pipeline) and, where CUDA is present, with gsplat's CUDA rasterizer.

Both renderers implement the same rules (``docs/render.md``); what differs is the arithmetic order
(log-space transmittance and 8-px ellipse-culled tiles in vadgs, cumprod over 16-px box tiles here)
and one visibility rule at the image border (below). Tolerances are therefore float64 round-off
for the images (measured ~1e-13) and float32 round-off in float32 (measured ~1e-6, depth ~1e-5 m);
the eps2d = 0.3 low-pass filter is the same in both (no allowance needed for it).
"""

from __future__ import annotations

import math

import pytest
import torch

from vadgs.render import RasterConfig, rasterize_gaussians

gsplat = pytest.importorskip("gsplat")

from vadgs.render.gsplat_backend import rasterize_gaussians_gsplat  # noqa: E402

IMAGES = ("color", "alpha", "depth", "normals")
TOL = {torch.float64: dict(image=1e-10, depth=1e-9, grad=1e-8), torch.float32: dict(image=1e-4, depth=1e-3)}


def _look_at(eye: list[float], target: list[float], dtype: torch.dtype) -> torch.Tensor:
    """world_to_cam of an OpenCV camera at ``eye`` looking at ``target``, world z up."""
    eye_t, tgt = torch.tensor(eye, dtype=dtype), torch.tensor(target, dtype=dtype)
    z = torch.nn.functional.normalize(tgt - eye_t, dim=0)
    x = torch.nn.functional.normalize(torch.linalg.cross(z, torch.tensor([0.0, 0, 1], dtype=dtype)), dim=0)
    y = torch.linalg.cross(z, x)
    rot = torch.stack([x, y, z])
    w2c = torch.eye(4, dtype=dtype)
    w2c[:3, :3] = rot
    w2c[:3, 3] = -rot @ eye_t
    return w2c


def street_scene(dtype: torch.dtype, n: int = 300, seed: int = 0, sh_degree: int = 1, opaque: bool = False):
    """Seeded Gaussians along a street (x forward, z up) and two car-mounted cameras (front, front-left)
    at 160×96 with a 60° horizontal field of view and an off-centre principal point."""
    g = torch.Generator().manual_seed(seed)
    means = torch.rand(n, 3, generator=g, dtype=dtype) * torch.tensor([30.0, 12.0, 4.0], dtype=dtype)
    means = means + torch.tensor([3.0, -6.0, -1.5], dtype=dtype)
    quats = torch.randn(n, 4, generator=g, dtype=dtype)
    scales = torch.exp(torch.rand(n, 3, generator=g, dtype=dtype) * 3.0 - 3.5)  # 0.03 .. 0.6 m
    opacities = torch.rand(n, generator=g, dtype=dtype) * 0.95 + 0.02
    if opaque:  # large, nearly opaque Gaussians: pixels reach T <= 1e-4 and stop
        scales, opacities = scales * 4.0, 0.9 + 0.099 * opacities
    sh = torch.randn(n, (sh_degree + 1) ** 2, 3, generator=g, dtype=dtype) * 0.4
    h, w = 96, 160
    f = 0.5 * w / math.tan(math.radians(30.0))
    K = torch.tensor([[f, 0, 0.5 * (w - 1) + 3.2], [0, f, 0.5 * (h - 1) - 2.1], [0, 0, 1]], dtype=dtype)
    w2c = torch.stack(
        [_look_at([0.0, 0, 0.5], [10.0, 0, 0], dtype), _look_at([0.0, 0.5, 0.5], [8.0, 5, 0], dtype)]
    )
    return (means, quats, scales, opacities, sh, w2c, K.expand(2, 3, 3).clone(), (h, w))


def _border_band(out, image_size) -> torch.Tensor:
    """Gaussians whose box edge lies within half a pixel outside the image: gsplat keeps them
    (``u + r > -0.5``, its pixels span ``[0, W]``), vadgs culls them (``u + r >= 0``)."""
    h, w = image_size
    u, v = out.means2d.detach().unbind(-1)
    rx, ry = out.radii[..., 0].to(u), out.radii[..., 1].to(u)
    gaps = torch.stack([u + rx, w - 1 - (u - rx), v + ry, h - 1 - (v - ry)], -1)
    return ((gaps > -0.5) & (gaps < 0)).any(-1)


class TestGsplatBackendTorch:
    """``impl="torch"``: gsplat's pure-torch reference functions, runs on the CPU."""

    def test_smoke_and_cardinality(self):
        scene = street_scene(torch.float32, n=40)
        ref = rasterize_gaussians(*scene)
        out = rasterize_gaussians_gsplat(*scene, impl="torch")
        for a, b in zip(ref, out):
            if a is None:
                assert b is None
            else:
                assert a.shape == b.shape and a.dtype == b.dtype, (a.shape, b.shape)
        assert (out.median_ids == -1).all() and (out.median_depth == 0).all()

    @pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
    @pytest.mark.parametrize("antialiased", [False, True])
    def test_images_match_vadgs(self, dtype, antialiased):
        scene = street_scene(dtype)
        cfg = RasterConfig(antialiased=antialiased)
        bg = torch.tensor([0.2, 0.5, 0.9], dtype=dtype)
        ref = rasterize_gaussians(*scene, background=bg, config=cfg)
        out = rasterize_gaussians_gsplat(*scene, background=bg, config=cfg, impl="torch")
        assert ref.alpha.amax() > 0.9 and (ref.alpha < 1e-3).any()  # a scene with content and gaps
        tol = TOL[dtype]
        for name in IMAGES:
            err = (getattr(ref, name) - getattr(out, name)).abs().max().item()
            assert err <= (tol["depth"] if name == "depth" else tol["image"]), (name, err)
        torch.testing.assert_close(out.means2d, ref.means2d, rtol=0, atol=tol["image"] * 100)
        torch.testing.assert_close(out.depths, ref.depths)
        # Visibility and radii agree except in the half-pixel border band (see _border_band).
        differ = out.visible != ref.visible
        assert not (differ & ~_border_band(out, scene[-1])).any()
        both = out.visible & ref.visible
        assert torch.equal(out.radii[both], ref.radii[both])

    @pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
    def test_opaque_scene_where_pixels_stop(self, dtype):
        scene = street_scene(dtype, opaque=True)
        ref = rasterize_gaussians(*scene)
        out = rasterize_gaussians_gsplat(*scene, impl="torch")
        # The scene exercises the stop rule: without it (transmittance_min = 0) pixels change.
        no_stop = rasterize_gaussians(*scene, config=RasterConfig(transmittance_min=0.0))
        assert (no_stop.alpha - ref.alpha).abs().amax() > 1e-5
        for name in IMAGES:
            err = (getattr(ref, name) - getattr(out, name)).abs().max().item()
            assert err <= (TOL[dtype]["depth"] if name == "depth" else TOL[dtype]["image"]), (name, err)

    def test_gradients_match_vadgs(self):
        dtype = torch.float64
        means, quats, scales, opac, sh, w2c, K, size = street_scene(dtype, n=120)
        leaves = [t.clone().requires_grad_(True) for t in (means, quats, scales, opac, sh)]
        target = torch.rand(2, 3, *size, generator=torch.Generator().manual_seed(1), dtype=dtype)
        grads = []
        for fn in (rasterize_gaussians, lambda *a: rasterize_gaussians_gsplat(*a, impl="torch")):
            out = fn(*leaves, w2c, K, size)
            loss = (out.color - target).square().sum() + 0.1 * out.depth.sum() + out.alpha.sum()
            loss.backward()
            grads.append([t.grad.clone() for t in leaves] + [out.means2d.grad])
            for t in leaves:
                t.grad = None
        for name, a, b in zip(("means", "quats", "scales", "opacities", "sh", "means2d"), *grads):
            err = (a - b).abs().max().item()
            assert err <= TOL[dtype]["grad"] * max(a.abs().max().item(), 1.0), (name, err)

    @pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
    def test_gaussian_in_a_cameras_plane_gets_no_gradient(self, dtype):
        """A Gaussian exactly in a camera's plane (z = 0) or behind it is culled, as CUDA culls it:
        no NaN in the backward (the torch reference divided by z = 0 there: the bundled sample's
        NaN at step 2), no gradient to it, and every other gradient as without it."""
        means, quats, scales, opac, sh, w2c, K, size = street_scene(dtype, n=60)
        w2c = w2c.clone()  # camera 0 at (0, 0, 0.5) looking along world x, exactly: z_cam = x_world
        w2c[0] = torch.tensor([[0.0, -1, 0, 0], [0, 0, -1, 0.5], [1, 0, 0, 0], [0, 0, 0, 1]], dtype=dtype)
        extra = torch.tensor([[0.0, 0.3, 0.6], [-2.0, 0.0, 0.5]], dtype=dtype)  # z = 0; z = -2
        assert (extra @ w2c[0, :3, :3].T + w2c[0, :3, 3])[:, 2].tolist() == [0.0, -2.0]
        target = torch.rand(2, 3, *size, generator=torch.Generator().manual_seed(1), dtype=dtype)
        grads, images = [], []
        for k in (0, 2):  # without and with the two Gaussians (camera 0's plane, behind camera 0)
            leaves = [
                torch.cat([means, extra[:k]]),
                torch.cat([quats, quats[:k]]),
                torch.cat([scales, scales[:k]]),
                torch.cat([opac, opac.new_full((k,), 0.9)]),
                torch.cat([sh, sh[:k]]),
            ]
            leaves = [x.clone().requires_grad_(True) for x in leaves]
            out = rasterize_gaussians_gsplat(*leaves, w2c[:1], K[:1], size, impl="torch")
            loss = (out.color - target[:1]).square().sum() + 0.1 * out.depth.sum() + out.alpha.sum()
            loss.backward()
            grads.append([x.grad for x in leaves])
            images.append(out.color.detach())
            assert (out.radii[0, 60:] == 0).all()
        assert torch.equal(images[0], images[1])
        for a, b in zip(*grads):
            assert torch.isfinite(b).all()
            assert torch.equal(b[60:], torch.zeros_like(b[60:]))
            torch.testing.assert_close(b[:60], a, rtol=0, atol=0)

    def test_one_gaussian_closed_form(self):
        # docs/render.md's worked example: alpha(u, v) = 0.8 exp(-|d|^2 / 8.6) around pixel (12, 10)
        # (a flat z scale does not change the screen covariance on the axis; it sets the normal).
        K = torch.tensor([[[40.0, 0, 12.0], [0, 40.0, 10.0], [0, 0, 1]]])
        out = rasterize_gaussians_gsplat(
            torch.tensor([[0.0, 0.0, 2.0]]), torch.tensor([[1.0, 0, 0, 0]]), torch.tensor([[0.1, 0.1, 0.02]]),
            torch.tensor([0.8]), torch.tensor([[0.9, 0.5, 0.1]]), torch.eye(4)[None], K, (21, 25),
        )  # fmt: skip
        assert out.alpha[0, 0, 10, 12].item() == pytest.approx(0.8, abs=1e-6)
        assert out.alpha[0, 0, 10, 14].item() == pytest.approx(0.8 * math.exp(-4 / 8.6), abs=1e-6)
        assert out.radii.tolist() == [[[7, 7]]]
        assert out.normals[0, :, 10, 12].tolist() == pytest.approx([0.0, 0.0, -1.0], abs=1e-6)

    def test_config_backend_dispatch(self):
        scene = street_scene(torch.float32, n=60)
        via_config = rasterize_gaussians(*scene, config=RasterConfig(backend="gsplat"))
        direct = rasterize_gaussians_gsplat(*scene)
        for name in IMAGES:
            assert torch.equal(getattr(via_config, name), getattr(direct, name)), name

    def test_exceptions(self):
        scene = street_scene(torch.float32, n=5)
        with pytest.raises(ValueError, match="impl"):
            rasterize_gaussians_gsplat(*scene, impl="triton")
        with pytest.raises(ValueError, match="CUDA tensors"):
            rasterize_gaussians_gsplat(*scene, impl="cuda")
        with pytest.raises(ValueError, match="alpha_max"):
            rasterize_gaussians_gsplat(*scene, config=RasterConfig(alpha_max=0.99))
        with pytest.raises(ValueError, match="absgrad"):
            rasterize_gaussians_gsplat(*scene, config=RasterConfig(absgrad=True), impl="torch")
        with pytest.raises(ValueError, match="sh_degree"):
            rasterize_gaussians_gsplat(*scene[:4], scene[4][:, :4], *scene[5:], sh_degree=2)
        with pytest.raises(ValueError, match="opacities"):  # the shared input checks
            rasterize_gaussians_gsplat(*scene[:3], scene[3] + 2.0, *scene[4:])
        with pytest.raises(ValueError, match="backend"):
            RasterConfig(backend="cuda")


def test_trainer_on_the_sample_stays_finite():
    """The trainer with gsplat's CPU path on the bundled sample: NaN at step 2 before culling
    matched CUDA's (a Gaussian exactly in a camera's plane); now every step is finite."""
    from vadgs.data import load_scene, sample_scene_path
    from vadgs.train.config import TrainConfig
    from vadgs.train.trainer import Trainer

    torch.manual_seed(0)
    cfg = TrainConfig(iterations=30, checkpoint_every=10**6, raster=RasterConfig(backend="gsplat"))
    with pytest.warns(UserWarning, match="no densification"):
        trainer = Trainer(load_scene(sample_scene_path(), scale=0.5), cfg, progress=False)
    losses = [trainer.train_step()["total"] for _ in range(4)]
    assert all(math.isfinite(x) for x in losses), losses
    assert all(torch.isfinite(p).all() for p in trainer.model.params.values())


@pytest.mark.skipif(not torch.cuda.is_available(), reason="gsplat's CUDA rasterizer needs a CUDA device")
class TestGsplatBackendCuda:
    """``impl="cuda"``: the real ``gsplat.rasterization`` against vadgs on the same GPU."""

    def test_images_and_means2d_grad_match_vadgs(self):
        scene = street_scene(torch.float32)
        means, quats, scales, opac, sh, w2c, K, size = (
            t.cuda() if isinstance(t, torch.Tensor) else t for t in scene
        )
        means = means.clone().requires_grad_(True)
        bg = torch.tensor([0.2, 0.5, 0.9], device="cuda")
        outs = []
        for fn in (rasterize_gaussians, lambda *a, **k: rasterize_gaussians_gsplat(*a, **k, impl="cuda")):
            out = fn(means, quats, scales, opac, sh, w2c, K, size, background=bg)
            (out.color.sum() + out.depth.sum()).backward()
            outs.append((out, means.grad.clone()))
            means.grad = None
        (ref, g_ref), (out, g_out) = outs
        for name in IMAGES:
            err = (getattr(ref, name) - getattr(out, name)).abs().max().item()
            assert err <= (1e-3 if name == "depth" else 1e-4), (name, err)
        both = out.visible & ref.visible
        # Both sum float32 terms of up to ~90 px^-1 in different orders (gsplat: atomicAdd per
        # tile): on an H100 (2026-11-27) 7 of 860 entries differed by up to 5.8e-4 = 6.5e-6 of the
        # largest entry (a fixed atol of 1e-4 failed there); a wrong footprint or weight moves them
        # by a fraction of their own size.
        g2d = ref.means2d.grad[both]
        torch.testing.assert_close(out.means2d.grad[both], g2d, rtol=1e-3, atol=3e-5 * g2d.abs().max().item())
        torch.testing.assert_close(g_out, g_ref, rtol=1e-3, atol=1e-3 * g_ref.abs().max().item())
