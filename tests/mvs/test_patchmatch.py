from __future__ import annotations

import types

import pytest
import torch
import torch.nn.functional as F

from vadgs.geometry import (
    apply_homography,
    cameras_in_object_frame,
    plane_homography,
    relative_pose,
    warp_patches,
)
from vadgs.mvs import (
    PatchMatch,
    PatchMatchConfig,
    PatchMatchResult,
    bilateral_ncc,
    bilateral_weights,
    patch_offsets,
    patchmatch,
    propagation_regions,
    reference_patches,
)
from vadgs.mvs.patchmatch import MatchPixels, map_tables, window_maps

from .mvs_scenes import plane_scene, texture

FAST = PatchMatchConfig(iterations=3)


def run(scene, config=FAST, **kw):
    return patchmatch(
        scene.image, scene.src_images, scene.K, scene.src_K, scene.world_to_cam,
        scene.src_world_to_cam, (1.0, 10.0), config, **kw,
    )  # fmt: skip


def disparity_error(scene, depth, baseline=0.15):
    """|f b / z - f b / z_gt| in pixels over the interior (a window from the border)."""
    f = float(scene.K[0, 0, 0])
    err = (f * baseline / depth.clamp_min(1e-6) - f * baseline / scene.depth).abs()
    return err[..., 6:-6, 6:-6]


class TestPlaneWarp:
    def test_fused_homography_matches_geometry(self, slanted_scene):
        """The fused per-pixel homography of the hot loop equals geometry.plane_homography."""
        sc = slanted_scene
        h, w = sc.depth.shape[-2:]
        K, v = sc.K, sc.src_images.shape[1]
        idx = torch.arange(0, h * w, 7)
        ys, xs = idx // w, idx % w
        pix = torch.stack([xs, ys, torch.ones_like(xs)], -1).float()
        rays = (pix @ torch.linalg.inv(K[0]).T)[None]
        depth = sc.depth.reshape(1, -1)[:, idx]
        normal = sc.normal.expand(1, idx.shape[0], 3)
        src_from_ref = relative_pose(sc.world_to_cam[:, None], sc.src_world_to_cam)
        norm = torch.tensor([[2 / (w - 1), 0, -1], [0, 2 / (h - 1), -1], [0, 0, 1]])
        A = norm @ sc.src_K @ src_from_ref[..., :3, :3] @ torch.linalg.inv(K)[:, None]
        b = (norm @ sc.src_K @ src_from_ref[..., :3, 3:]).squeeze(-1)
        cols, rows = map_tables(A, torch.linalg.inv(K), pix, rays)
        src = types.SimpleNamespace(b=b, nan=torch.tensor(float("nan")))
        hyp = torch.cat([depth[..., None], normal], -1)[:, None]  # (1, K=1, P, 4)
        C, nr = window_maps(src, MatchPixels(idx, rays, cols, rows, None), hyp)
        assert (nr < -1e-6).all()
        off = torch.tensor([[0.0, 0.0], [3.0, -2.0], [-5.0, 5.0]])
        for j in range(v):
            dist = -depth * (normal * rays).sum(-1)
            H = plane_homography(K, sc.src_K[:, j], src_from_ref[:, j], normal, dist)  # (1, P, 3, 3)
            for o in off:
                want = apply_homography(H, pix[None, :, :2] + o)
                xyz = torch.cat([o, torch.ones(1)]) @ C[0, j, :, 0].transpose(0, 1)  # (P, 3)
                got = xyz[:, :2] / xyz[:, 2:]
                got = (got + 1) / 2 * torch.tensor([w - 1.0, h - 1.0])
                assert torch.allclose(got, want[0], atol=1e-3)

    def test_true_plane_has_zero_cost(self, slanted_scene):
        """Warping a window through the true plane with geometry.warp_patches reproduces it."""
        sc = slanted_scene
        h, w = sc.depth.shape[-2:]
        off = patch_offsets(3, 1)
        ys, xs = torch.meshgrid(torch.arange(8, h - 8), torch.arange(8, w - 8), indexing="ij")
        centers = torch.stack([xs, ys], -1).reshape(-1, 2).float()
        pix = torch.cat([centers, torch.ones(centers.shape[0], 1)], -1)
        rays = pix @ torch.linalg.inv(sc.K[0]).T
        z = sc.depth[0, 0, ys.reshape(-1), xs.reshape(-1)]
        dist = -z * (rays @ sc.normal)
        src_from_ref = relative_pose(sc.world_to_cam, sc.src_world_to_cam[:, 0])
        H = plane_homography(sc.K, sc.src_K[:, 0], src_from_ref, sc.normal.expand(1, len(z), 3), dist[None])
        patches, inside = warp_patches(sc.src_images[:, 0], H, centers, off)
        ref = reference_patches(sc.image, off)[0].T.reshape(h, w, -1)[ys.reshape(-1), xs.reshape(-1)]
        wts = bilateral_weights(ref, off, 3.0, 0.2)
        cost = bilateral_ncc(ref, patches[0, 0], wts)
        assert inside.float().mean() > 0.9
        assert cost[inside.all(-1)[0]].median() < 0.03  # two bilinear resamplings, not exactly 0
        # a wrong depth costs more
        H_bad = plane_homography(
            sc.K, sc.src_K[:, 0], src_from_ref, sc.normal.expand(1, len(z), 3), 1.2 * dist[None]
        )
        bad, _ = warp_patches(sc.src_images[:, 0], H_bad, centers, off)
        assert bilateral_ncc(ref, bad[0, 0], wts).median() > 5 * cost.median()


class TestPatchMatch:
    def test_smoke(self, fronto_scene):
        res = run(fronto_scene)
        assert isinstance(res, PatchMatchResult)

    def test_cardinality(self, fronto_scene):
        res = run(fronto_scene, PatchMatchConfig(iterations=1))
        h, w = fronto_scene.depth.shape[-2:]
        assert res.depth.shape == (1, 1, h, w)
        assert res.normal.shape == (1, 3, h, w)
        assert res.cost.shape == (1, 1, h, w)
        assert res.view_costs.shape == (1, 3, h, w)
        assert res.mask.shape == (1, 1, h, w) and res.mask.dtype == torch.bool

    def test_fronto_parallel_subpixel(self, fronto_scene):
        res = run(fronto_scene)
        err = disparity_error(fronto_scene, res.raw_depth)
        assert err.median() < 0.05
        assert (err < 0.5).float().mean() > 0.95
        n = res.normal[0, :, 6:-6, 6:-6].reshape(3, -1)[:, res.mask[0, 0, 6:-6, 6:-6].reshape(-1)]
        assert (n[2] < -0.95).float().mean() > 0.9  # facing the camera, fronto-parallel

    def test_slanted_subpixel(self, slanted_scene):
        res = run(slanted_scene, PatchMatchConfig(iterations=4))
        err = disparity_error(slanted_scene, res.raw_depth)
        assert err.median() < 0.1
        assert (err < 0.5).float().mean() > 0.9
        m = res.mask[0, 0, 6:-6, 6:-6].reshape(-1)
        n = res.normal[0, :, 6:-6, 6:-6].reshape(3, -1)[:, m]
        assert (n.T @ slanted_scene.normal).median() > 0.98

    @pytest.mark.parametrize("levels", [1, 2])
    def test_slanted_subpixel_at_every_pyramid_depth(self, slanted_scene, levels):
        cfg = PatchMatchConfig(iterations=4, pyramid_levels=levels, seed=1)
        err = disparity_error(slanted_scene, run(slanted_scene, cfg).raw_depth)
        assert err.median() < 0.1
        assert (err < 0.5).float().mean() > 0.85

    def test_slanted_three_levels(self, slanted_scene):
        """Three levels on 40x56 search a 10x14 coarsest image with 11x11 windows: the result
        depends on the seed (median error 0.05 to 0.19 px over seeds 0-5, before and after the
        batched half-sweeps of issue 48), so the typical seed is checked, not a lucky one."""
        errs = []
        for seed in range(4):
            cfg = PatchMatchConfig(iterations=4, pyramid_levels=3, seed=seed)
            err = disparity_error(slanted_scene, run(slanted_scene, cfg).raw_depth)
            assert (err < 0.5).float().mean() > 0.85
            errs.append(float(err.median()))
        assert sorted(errs)[len(errs) // 2] < 0.15, errs

    def test_pyramid_keeps_a_full_resolution_init(self, slanted_scene):
        """The fine level scores the caller's init against the upsampled coarse planes."""
        sc = slanted_scene
        n = sc.normal.reshape(1, 3, 1, 1).expand(1, 3, *sc.depth.shape[-2:])
        cfg = PatchMatchConfig(iterations=1, pyramid_levels=2, num_refine=0)
        exact = run(sc, cfg, init_depth=sc.depth, init_normal=n)
        coarse_only = run(sc, cfg)
        err = disparity_error(sc, exact.raw_depth).median()
        assert err < 0.03
        assert err < disparity_error(sc, coarse_only.raw_depth).median()

    def test_bad_pyramid_settings(self):
        with pytest.raises(ValueError, match="pyramid_levels"):
            PatchMatchConfig(pyramid_levels=0)
        with pytest.raises(ValueError, match="fine_propagation"):
            PatchMatchConfig(fine_propagation="diagonal")

    def test_multi_view_beats_two_view(self):
        """More sources constrain better (and batching B > 1 works)."""
        sc = plane_scene(normal=(0.2, 0.1, -1.0), seed=3)
        both = patchmatch(
            torch.cat([sc.image, sc.image]),
            torch.cat([sc.src_images, sc.src_images]),
            sc.K.repeat(2, 1, 1), sc.src_K.repeat(2, 1, 1, 1), sc.world_to_cam.repeat(2, 1, 1),
            sc.src_world_to_cam.repeat(2, 1, 1, 1), (1.0, 10.0), FAST,
        )  # fmt: skip
        assert both.depth.shape[0] == 2
        assert disparity_error(sc, both.raw_depth[:1]).median() < 0.1
        assert disparity_error(sc, both.raw_depth[1:]).median() < 0.1

    @pytest.mark.parametrize("selection", ["acmh", "topk"])
    def test_view_selection_survives_an_occluded_view(self, selection):
        sc = plane_scene(baselines=((0.15, 0, 0), (-0.15, 0, 0), (0, 0.12, 0), (0.1, 0.1, 0)), seed=4)
        src = sc.src_images.clone()
        src[:, 3] = texture(*src.shape[-2:], seed=99)  # one view sees something else entirely
        sc = sc._replace(src_images=src)
        res = run(sc, PatchMatchConfig(iterations=3, view_selection=selection))
        assert disparity_error(sc, res.raw_depth).median() < 0.1
        assert res.view_costs[0, 3, 6:-6, 6:-6].median() > 0.5  # the bad view stays bad

    def test_init_from_depth_and_normal(self, slanted_scene):
        sc = slanted_scene
        h, w = sc.depth.shape[-2:]
        n = sc.normal.reshape(1, 3, 1, 1).expand(1, 3, h, w)
        res = run(sc, PatchMatchConfig(iterations=0), init_depth=sc.depth, init_normal=-n)  # flipped: fixed
        assert torch.allclose(res.raw_depth, sc.depth.clamp(1, 10))
        assert res.cost[0, 0, 6:-6, 6:-6].median() < 0.05
        # a perturbed init converges in one iteration
        res1 = run(sc, PatchMatchConfig(iterations=1), init_depth=sc.depth * 1.03, init_normal=n)
        assert disparity_error(sc, res1.raw_depth).median() < 0.15

    def test_mask_restricts_the_region(self, fronto_scene):
        sc = fronto_scene
        mask = torch.zeros_like(sc.depth, dtype=torch.bool)
        mask[..., :, : mask.shape[-1] // 2] = True
        res = run(sc, mask=mask)
        assert not res.mask[~mask].any()
        assert (res.depth[~mask] == 0).all()
        assert disparity_error(sc, res.raw_depth)[..., :, :15].median() < 0.1

    def test_src_masks_block_views(self, fronto_scene):
        sc = fronto_scene
        src_masks = torch.ones_like(sc.src_images[:, :, :1], dtype=torch.bool)
        src_masks[:, 0] = False
        res = run(sc, src_masks=src_masks)
        assert (res.view_costs[:, 0] == 2).all()

    def test_textureless_and_sky_all_invalid(self, fronto_scene):
        sc = fronto_scene
        for img in (torch.full_like(sc.image, 0.5), torch.zeros_like(sc.image)):
            src = img[:, None].expand_as(sc.src_images)
            res = run(sc._replace(image=img, src_images=src), PatchMatchConfig(iterations=1))
            assert not res.mask.any()
            assert torch.isfinite(res.raw_depth).all() and (res.depth == 0).all()

    def test_no_nan_marked_valid(self, fronto_scene):
        res = run(fronto_scene)
        assert torch.isfinite(res.depth).all() and torch.isfinite(res.normal).all()
        assert (res.depth[res.mask] > 0).all()
        norms = res.normal.norm(dim=1, keepdim=True)[res.mask]
        assert torch.allclose(norms, torch.ones_like(norms), atol=1e-4)

    def test_exceptions(self, fronto_scene):
        sc = fronto_scene
        with pytest.raises(ValueError, match="at least one source"):
            run(sc._replace(src_images=sc.src_images[:, :0], src_K=sc.src_K[:, :0],
                            src_world_to_cam=sc.src_world_to_cam[:, :0]))  # fmt: skip
        with pytest.raises(ValueError, match="src_images"):
            run(sc._replace(src_images=sc.src_images.expand(1, 3, 3, *sc.image.shape[-2:])))
        with pytest.raises(ValueError, match="src_K"):
            run(sc._replace(src_K=sc.src_K[:, :2]))
        with pytest.raises(ValueError, match="init_depth"):
            run(sc, init_depth=torch.ones(1, 1, 5, 5))
        with pytest.raises(ValueError, match="depth_range"):
            patchmatch(
                sc.image, sc.src_images, sc.K, sc.src_K, sc.world_to_cam, sc.src_world_to_cam, (0.0, 1.0)
            )
        with pytest.raises(ValueError, match="propagation"):
            PatchMatchConfig(propagation="diagonal")
        bad = sc.world_to_cam.clone()
        bad[0, 3, 0] = 0.5  # not a rigid transform
        with pytest.raises(ValueError, match=r"world_to_cam: expected a transform with last row .*\[0.5, 0"):
            run(sc._replace(world_to_cam=bad))
        with pytest.raises(ValueError, match="world_to_cam: expected finite"):
            run(sc._replace(world_to_cam=sc.world_to_cam * float("nan")))

    def test_degenerate_baseline(self, fronto_scene):
        sc = fronto_scene
        same = sc.world_to_cam[:, None].expand_as(sc.src_world_to_cam).clone()
        with pytest.raises(ValueError, match="baseline"):
            run(sc._replace(src_world_to_cam=same))
        # one degenerate source among good ones is ignored
        part = sc.src_world_to_cam.clone()
        part[:, 2] = sc.world_to_cam
        res = run(sc._replace(src_world_to_cam=part))
        assert (res.view_costs[:, 2] == 2).all()
        assert disparity_error(sc, res.raw_depth).median() < 0.1

    def test_object_frame(self, fronto_scene):
        """A plane moving with an object, seen by a camera that does not move: degenerate in the
        world frame, solved in the object frame (cameras_in_object_frame)."""
        sc = fronto_scene
        v = sc.src_images.shape[1]
        w2c_world = torch.eye(4).expand(1, v, 4, 4)  # the same static camera at every frame
        obj_ref = torch.eye(4)[None]
        # object_to_world per source frame, chosen so that object_to_cam = the scene's source poses
        obj_src = sc.src_world_to_cam.clone()
        with pytest.raises(ValueError, match="baseline"):
            run(sc._replace(src_world_to_cam=w2c_world.clone()))
        w2c_obj = cameras_in_object_frame(w2c_world.reshape(v, 4, 4), obj_src.reshape(v, 4, 4)).reshape(
            1, v, 4, 4
        )
        ref_obj = cameras_in_object_frame(sc.world_to_cam, obj_ref)
        res = run(sc._replace(world_to_cam=ref_obj, src_world_to_cam=w2c_obj))
        assert disparity_error(sc, res.raw_depth).median() < 0.05

    def test_module_equals_function(self, fronto_scene):
        sc = fronto_scene
        cfg = PatchMatchConfig(iterations=1, seed=3)
        a = PatchMatch(cfg)(
            sc.image, sc.src_images, sc.K, sc.src_K, sc.world_to_cam, sc.src_world_to_cam, (1.0, 10.0)
        )
        b = run(sc, cfg)
        assert torch.equal(a.raw_depth, b.raw_depth) and torch.equal(a.normal, b.normal)

    def test_seeded_deterministic(self, fronto_scene):
        a, b = run(fronto_scene), run(fronto_scene)
        assert torch.equal(a.raw_depth, b.raw_depth)

    def test_rgb_and_float64(self):
        sc = plane_scene(size=(24, 32))
        rgb = sc.image.expand(1, 3, 24, 32)
        res = patchmatch(
            rgb.double(), sc.src_images.expand(1, 3, 3, 24, 32).double(), sc.K.double(), sc.src_K.double(),
            sc.world_to_cam.double(), sc.src_world_to_cam.double(), (1.0, 10.0),
            PatchMatchConfig(iterations=1),
        )  # fmt: skip
        assert res.depth.dtype == torch.float64


class TestPropagationRegions:
    def test_checkerboard_parity(self):
        for kind in ("acmh", "cross"):
            for region in propagation_regions(kind):
                assert all((dx + dy) % 2 == 1 for dx, dy in region)

    def test_cardinality(self):
        assert len(propagation_regions("cross")) == 4
        assert sum(len(r) for r in propagation_regions()) == 72


def test_cross_propagation_converges(fronto_scene):
    res = run(fronto_scene, PatchMatchConfig(iterations=4, propagation="cross"))
    assert disparity_error(fronto_scene, res.raw_depth).median() < 0.1


def test_gray_conversion_of_two_channels(fronto_scene):
    sc = fronto_scene
    two = F.pad(sc.image, (0, 0, 0, 0, 0, 1), value=0.0) * 2  # (1, 2, H, W): mean equals the image
    res = run(
        sc._replace(image=two, src_images=F.pad(sc.src_images, (0, 0, 0, 0, 0, 1)) * 2),
        PatchMatchConfig(iterations=2),
    )
    assert res.depth.shape[1] == 1


class TestPatchMatchRejectsWhatItCannotHandle:
    """Reliability trial (issue 17): uint8, tiny and NaN images are named errors."""

    def _run(self, image, src):
        K = torch.tensor([[[8.0, 0, 4.0], [0, 8.0, 4.0], [0, 0, 1]]])
        s2c = torch.eye(4)[None, None].clone()
        s2c[0, 0, 0, 3] = -0.2
        return patchmatch(image, src, K, K[:, None], torch.eye(4)[None], s2c, (1.0, 10.0), FAST)

    def test_uint8(self):
        img = torch.zeros(1, 1, 16, 16, dtype=torch.uint8)
        with pytest.raises(ValueError, match=r"image: expected a floating dtype .*got torch.uint8"):
            self._run(img, img.float()[:, None])
        with pytest.raises(ValueError, match=r"src_images: expected a floating dtype"):
            self._run(img.float(), img[:, None])

    @pytest.mark.parametrize("size", [(0, 0), (1, 1), (5, 40)])
    def test_too_small(self, size):
        img = torch.rand(1, 1, *size)
        big = torch.rand(1, 1, 1, 16, 16)
        with pytest.raises(
            ValueError, match=rf"image: expected \(H, W\) of at least \(6, 6\) .*got \({size[0]}, {size[1]}\)"
        ):
            self._run(img, big)
        with pytest.raises(ValueError, match=r"src_images: expected \(H, W\) of at least \(6, 6\)"):
            self._run(big[:, 0], img[:, None])

    def test_nan(self):
        img = torch.rand(1, 1, 16, 16)
        img[0, 0, 3, 3] = float("nan")
        with pytest.raises(ValueError, match=r"image: expected finite values, got 1 non-finite of 256"):
            self._run(img, torch.rand(1, 1, 1, 16, 16))
        from vadgs.checks import checking

        with checking(False):  # a value check: off in a trusted loop
            self._run(img, torch.rand(1, 1, 1, 16, 16))


@pytest.mark.parametrize("cfg", [PatchMatchConfig(iterations=1, pyramid_levels=1), PatchMatchConfig()])
def test_equivariant_to_the_scale_of_the_world(cfg):
    """The world and the depth range scaled by 1/20: the same depths / 20, the same normals and costs.

    A candidate of fixed absolute depth (the batched path's padding plane, before it was replaced by
    the pixel's own) moved 14 % of the depths of this scene by more than 1 %.
    """
    sc = plane_scene(normal=(0.3, -0.2, -1.0), size=(40, 56))
    out = {}
    for s in (1.0, 1 / 20):
        w2c, sw2c = sc.world_to_cam.clone(), sc.src_world_to_cam.clone()
        w2c[..., :3, 3] *= s
        sw2c[..., :3, 3] *= s
        out[s] = patchmatch(sc.image, sc.src_images, sc.K, sc.src_K, w2c, sw2c, (0.5 * s, 5.0 * s), cfg)
    a, b = out[1.0], out[1 / 20]
    # Rounding differs between the two scales, so near-ties of the search can go the other way
    # (1.1 % of the depths off by > 1e-3 with the default pyramid, 0.13 % with the per-candidate
    # path of before): none by > 1 %.
    rel = (a.raw_depth - 20 * b.raw_depth).abs() / a.raw_depth
    assert float((rel > 1e-2).float().mean()) == 0.0
    assert float((rel > 1e-3).float().mean()) < 0.02
    assert torch.equal(a.mask, b.mask)
    torch.testing.assert_close(a.cost, b.cost, atol=2e-3, rtol=0)
