"""Tests of :mod:`vadgs.train.vad.fusion`: steps 4–6 of an instance's reconstruction.

Ground truth: a known plane ``n . X = d`` seen by three cameras (identity rotations, centres on a
line across it); each member's depth is the plane's z-depth at its pixels, so a fused point must lie
on the plane, with the plane's normal and the colour of its pixel. The render comparisons of step 5a
the LiDAR check of step 5 and the resampling of step 6 are checked against loops over the pixels.
"""

from __future__ import annotations

import pytest
import torch

from vadgs.geometry.points import thin_points
from vadgs.mvs.patchmatch import PatchMatchResult
from vadgs.train.vad.crops import Crops, MatchedCrops, MatchScale
from vadgs.train.vad.fusion import (
    ConsistentDepth,
    consistent_depth,
    depth_priors,
    explained_pixels,
    fuse_points,
    lidar_check,
)
from vadgs.train.vad.reconstruct import ViewRender
from vadgs.train.vad.reconstruct_config import ReconstructConfig

H = W = 24
FOCAL = 30.0
CENTRES = ((-0.3, 0.0, 0.0), (0.0, 0.05, 0.0), (0.3, 0.0, 0.0))  # camera centres
NORMAL = torch.nn.functional.normalize(torch.tensor([0.2, -0.1, 1.0]), dim=0)  # the plane's
OFFSET = 4.0  # the plane: NORMAL . X = OFFSET (about 4 m in front of the cameras)


def plane_views() -> dict[str, torch.Tensor]:
    """The three members: ``K``, ``world_to_cam``, the plane's depth and camera-frame normals."""
    b = len(CENTRES)
    K = torch.tensor([[FOCAL, 0.0, (W - 1) / 2], [0.0, FOCAL, (H - 1) / 2], [0.0, 0.0, 1.0]]).repeat(b, 1, 1)
    centres = torch.tensor(CENTRES)
    w2c = torch.eye(4).repeat(b, 1, 1)
    w2c[:, :3, 3] = -centres  # identity rotations: the camera frame is the world's, shifted
    ys, xs = torch.meshgrid(
        torch.arange(H, dtype=torch.float32), torch.arange(W, dtype=torch.float32), indexing="ij"
    )
    rays = torch.stack([(xs - K[0, 0, 2]) / FOCAL, (ys - K[0, 1, 2]) / FOCAL, torch.ones_like(xs)])  # z = 1
    depth = (OFFSET - centres @ NORMAL)[:, None, None] / (NORMAL @ rays.reshape(3, -1)).reshape(1, H, W)
    normal = (-NORMAL)[None, :, None, None].expand(b, 3, H, W).clone()  # facing the cameras
    images = torch.rand(b, 3, H, W, generator=torch.Generator().manual_seed(0))
    return {"K": K, "w2c": w2c, "depth": depth[:, None], "normal": normal, "images": images}


def matched_crops(depth: torch.Tensor, views: dict[str, torch.Tensor]) -> MatchedCrops:
    """PatchMatch's result of the members as ``depth`` (every pixel estimated), with the crops' inputs."""
    b = depth.shape[0]
    mask = torch.ones(b, 1, H, W, dtype=torch.bool)
    result = PatchMatchResult(
        depth, views["normal"], torch.zeros(b, 1, H, W), torch.zeros(b, 2, H, W), mask, depth, views["normal"]
    )
    return MatchedCrops(result, views["images"], mask, views["K"], views["w2c"])


def crops_of(
    members: list[int], corners: list[tuple[int, int]], size: tuple[int, int], scale: MatchScale
) -> Crops:
    """The parts of :class:`Crops` that steps 4–6 read (members, corners, sizes, scale)."""
    f_up, f_down = scale.up, scale.down
    size_lo = (size[0] * f_down // f_up, size[1] * f_down // f_up)
    corners_lo = [(y * f_down // f_up, x * f_down // f_up) for y, x in corners]
    empty = torch.zeros(0)
    return Crops(members, empty, [], empty, empty, corners, size, corners_lo, size_lo, scale)


def plane_residual(points: torch.Tensor) -> torch.Tensor:
    return (points @ NORMAL - OFFSET).abs()


class TestConsistentDepth:
    def test_plane_kept_inconsistent_block_rejected(self):
        views = plane_views()
        depth = views["depth"].clone()
        depth[1, :, 6:14, 6:14] *= 1.2  # member 1 is wrong there: no other member agrees
        matched = matched_crops(depth, views)
        crops = crops_of([0, 1, 2], [(0, 0)] * 3, (H, W), MatchScale())
        cfg = ReconstructConfig(max_reproj_error=1.0, max_rel_depth=0.01, min_consistent_views=1, planar=None)
        cons = consistent_depth(matched, crops, [0, 1, 2], views["w2c"], False, cfg, None)
        assert isinstance(cons, ConsistentDepth)
        assert cons.keep.shape == (3, 1, H, W) and cons.keep.dtype == torch.bool
        assert not cons.keep[1, :, 6:14, 6:14].any()  # the inconsistent pixels: all rejected
        # every kept pixel is on the plane (its depth is the true one), with the plane's normal
        truth = views["depth"]
        assert torch.equal(cons.depth[cons.keep], truth[cons.keep])
        assert torch.equal(cons.normal, views["normal"])
        # the others: the disparity is at most 3 px, so all but a border that no other member sees
        good = torch.ones(3, 1, H, W, dtype=torch.bool)
        good[1, :, 6:14, 6:14] = False
        inner = good.clone()
        inner[..., :4] = inner[..., -4:] = False
        assert cons.keep[inner].all()
        assert 0.9 < cons.keep[good].float().mean() <= 1.0

    def test_two_confirmations_needed(self):
        """``min_consistent_views=2``: a pixel of member 0 seen by member 1 in its wrong block falls."""
        views = plane_views()
        depth = views["depth"].clone()
        depth[1, :, 6:14, 6:14] *= 1.2
        matched = matched_crops(depth, views)
        crops = crops_of([0, 1, 2], [(0, 0)] * 3, (H, W), MatchScale())
        one = ReconstructConfig(min_consistent_views=1, planar=None)
        two = ReconstructConfig(min_consistent_views=2, planar=None)
        keep1 = consistent_depth(matched, crops, [0, 1, 2], views["w2c"], False, one, None).keep
        keep2 = consistent_depth(matched, crops, [0, 1, 2], views["w2c"], False, two, None).keep
        assert (keep2 <= keep1).all()  # stricter
        # member 0's pixels at the block's centre project into member 1's wrong block (disparity < 3 px)
        assert keep1[0, :, 9:11, 9:11].all() and not keep2[0, :, 9:11, 9:11].any()


class TestFusePoints:
    def setup_method(self):
        self.views = plane_views()
        self.matched = matched_crops(self.views["depth"], self.views)
        keep = torch.ones(3, 1, H, W, dtype=torch.bool)
        keep[:, :, :2] = False  # two rows not consistent
        self.cons = ConsistentDepth(self.views["depth"], self.views["normal"], keep)
        self.new = keep.clone()
        self.new[:, :, 10:12, 10:12] = False  # explained: consistent, but no new point
        self.crops = crops_of([0, 1, 2], [(0, 0)] * 3, (H, W), MatchScale())

    def fuse(self, cfg, occupied=None, generator=None):
        return fuse_points(
            None,
            self.cons,
            self.matched,
            self.crops,
            self.new,
            0,
            cfg,
            occupied,
            generator,
            torch.device("cpu"),
        )  # track 0: a moving object's own frame (the index is not read)

    def test_points_on_the_plane(self):
        points, normals, colors, spacing, consistent = self.fuse(ReconstructConfig(thin_points=False))
        n_new = int(self.new.sum())
        assert points.shape == (n_new, 3) and normals.shape == (n_new, 3) and colors.shape == (n_new, 3)
        assert consistent == int(self.cons.keep.sum())
        assert plane_residual(points).max() < 1e-5  # on the plane (float32 at 4 m)
        assert torch.allclose(normals, (-NORMAL).expand(n_new, 3), atol=1e-6)
        # one point per new pixel, in view then pixel order: its colour and footprint z / f
        b, _, y, x = torch.nonzero(self.new, as_tuple=True)
        assert torch.equal(colors, self.views["images"][b, :, y, x])
        assert torch.allclose(spacing, self.views["depth"][b, 0, y, x] / FOCAL, rtol=1e-6)
        # each point projects back to its own pixel
        cam = points - torch.tensor(CENTRES)[b]
        assert torch.allclose(cam[:, 0] / cam[:, 2] * FOCAL + (W - 1) / 2, x.float(), atol=1e-3)
        assert torch.allclose(cam[:, 1] / cam[:, 2] * FOCAL + (H - 1) / 2, y.float(), atol=1e-3)

    def test_thinned_one_per_cell(self):
        full, _, _, full_spacing, _ = self.fuse(ReconstructConfig(thin_points=False))
        points, _, _, spacing, consistent = self.fuse(ReconstructConfig(thin_points=True))
        assert consistent == int(self.cons.keep.sum())
        cell = full_spacing.median()  # one cell of the median footprint (scale 1: no factor)
        # the reference: the first point of each cell, in priority order, by a loop
        seen, rows = set(), []
        for r, p in enumerate(full):
            key = tuple(torch.floor(p / cell).long().tolist())
            if key not in seen:
                seen.add(key)
                rows.append(r)
        assert torch.equal(points, full[rows]) and torch.equal(spacing, full_spacing[rows])
        assert 0 < points.shape[0] < full.shape[0] and plane_residual(points).max() < 1e-5

    def test_occupied_cells_give_nothing(self):
        full = self.fuse(ReconstructConfig(thin_points=False))[0]
        points, normals, colors, spacing, _ = self.fuse(ReconstructConfig(thin_points=True), occupied=full)
        assert points.shape == (0, 3) and normals.shape == (0, 3) and colors.shape == (0, 3)
        assert spacing.shape == (0,)
        # the cells of the points left of x = 0 taken: only points right of it, thinned
        full_spacing = self.fuse(ReconstructConfig(thin_points=False))[3]
        taken = full[full[:, 0] < 0]
        points = self.fuse(ReconstructConfig(thin_points=True), occupied=taken)[0]
        assert torch.equal(points, full[thin_points(full, full_spacing.median(), taken)])
        right = full[full[:, 0] >= 0]
        assert torch.equal(points, right[thin_points(right, full_spacing.median())])
        assert (points[:, 0] >= 0).all() and points.shape[0] > 0

    def test_max_points_a_seeded_subset(self):
        full = self.fuse(ReconstructConfig(thin_points=False))[0]
        cfg = ReconstructConfig(thin_points=False, max_points=50)
        a = self.fuse(cfg, generator=torch.Generator().manual_seed(3))[0]
        b = self.fuse(cfg, generator=torch.Generator().manual_seed(3))[0]
        assert a.shape == (50, 3) and torch.equal(a, b)
        # every point is one of the full set's, none twice
        match = (a[:, None] == full[None]).all(-1)
        assert (match.sum(1) == 1).all() and match.any(0).sum() == 50
        one_less = self.fuse(ReconstructConfig(thin_points=False, max_points=full.shape[0] - 1))[0]
        assert one_less.shape[0] == full.shape[0] - 1
        at_cap = self.fuse(ReconstructConfig(thin_points=False, max_points=full.shape[0]))[0]
        assert torch.equal(at_cap, full)  # not more than the cap: all, in order


class _Unpadded:
    """The index as :func:`~vadgs.train.vad.crops.render_maps` reads it: views already of its size."""

    def pad(self, x: torch.Tensor) -> torch.Tensor:
        return x


class TestExplainedPixels:
    size = (16, 18)  # the views' (H, W)

    def case(self, scale: MatchScale):
        g = torch.Generator().manual_seed(1)
        crop = (6 * scale.up // scale.down, 8 * scale.up // scale.down)  # at the matching scale
        crops = crops_of([0, 1], [(2 * scale.up // scale.down, 4 * scale.up // scale.down)] * 2, crop, scale)
        mvs = 2.0 + torch.rand(2, 1, *crop, generator=g)
        keep = torch.rand(2, 1, *crop, generator=g) > 0.2
        cons = ConsistentDepth(mvs, torch.zeros(2, 3, *crop), keep)
        renders = {}
        for view in (7, 9):  # the group's views
            d = 2.0 + 0.5 * torch.rand(1, *self.size, generator=g)
            d[torch.rand(1, *self.size, generator=g) < 0.1] = 0.0
            a = torch.rand(1, *self.size, generator=g)
            renders[view] = ViewRender(d, a, torch.zeros(3, *self.size))
        return crops, cons, renders

    def reference(self, crops, cons, renders, group, cfg):
        """A loop over the members' crop pixels, the render resampled to the matching scale."""
        up, down = crops.scale.up, crops.scale.down
        ch, cw = crops.size
        out = torch.zeros_like(cons.keep)
        for k, (i, (y0, x0)) in enumerate(zip(crops.members, crops.corners)):
            r = renders[group[i]]
            for y in range(ch):
                for x in range(cw):
                    Y, X = y0 + y, x0 + x  # at the matching scale
                    if up > 1:
                        d, a = float(r.depth[0, Y // up, X // up]), float(r.alpha[0, Y // up, X // up])
                    else:
                        block = r.depth[0, Y * down : (Y + 1) * down, X * down : (X + 1) * down]
                        valid = block > 0
                        d = float(block[valid].mean()) if valid.float().mean() >= 0.5 else 0.0
                        a = float(r.alpha[0, Y * down : (Y + 1) * down, X * down : (X + 1) * down].mean())
                    m = float(cons.depth[k, 0, y, x])
                    hit = a >= cfg.explained_alpha and d > 0 and d <= m * (1 + cfg.explained_tolerance)
                    out[k, 0, y, x] = hit and bool(cons.keep[k, 0, y, x])
        return out

    @pytest.mark.parametrize("scale", [MatchScale(), MatchScale(up=2), MatchScale(down=2)])
    def test_against_a_loop(self, scale):
        crops, cons, renders = self.case(scale)
        cfg = ReconstructConfig(explained_alpha=0.5, explained_tolerance=0.05)
        got = explained_pixels(_Unpadded(), cons, crops, [7, 9], cfg, renders.__getitem__)
        want = self.reference(crops, cons, renders, [7, 9], cfg)
        assert got.dtype == torch.bool and got.shape == cons.keep.shape
        assert torch.equal(got, want)
        assert 0 < int(got.sum()) < int(cons.keep.sum())  # the case has both kinds

    def test_no_render_or_no_alpha_explains_nothing(self):
        crops, cons, renders = self.case(MatchScale())
        cfg = ReconstructConfig()
        assert not explained_pixels(_Unpadded(), cons, crops, [7, 9], cfg, None).any()
        pairs = {v: (r.depth, r.normals) for v, r in renders.items()}  # (depth, normals): no alpha
        assert not explained_pixels(_Unpadded(), cons, crops, [7, 9], cfg, pairs.__getitem__).any()


class _Sweeps:
    """The index as :func:`lidar_check` reads it: each view's own measured depth."""

    def __init__(self, depth: dict[int, torch.Tensor]):
        self.depth = depth

    def observed_depth(self, view: int, track: int | None = None) -> torch.Tensor:
        return self.depth[view]


class TestLidarCheck:
    size = (16, 18)  # the views' (H, W)

    def case(self, scale: MatchScale):
        """MVS depth near 2-3 m; each view's sweep measured 60 % of the pixels, a third of those
        20 % nearer than the MVS surface (a surface the matches put behind it)."""
        g = torch.Generator().manual_seed(3)
        up, down = scale.up, scale.down
        crop = (6 * up // down, 8 * up // down)  # at the matching scale
        corner = (2 * up // down, 4 * up // down)
        crops = crops_of([0, 1], [corner] * 2, crop, scale)
        mvs = 2.0 + torch.rand(2, 1, *crop, generator=g)
        keep = torch.rand(2, 1, *crop, generator=g) > 0.2
        sweeps = {}
        for k, view in enumerate((7, 9)):
            d = torch.zeros(1, *self.size)
            # the MVS depth at the scene's resolution (a block's value for every pixel of it)
            block = mvs[k] if up == 1 and down == 1 else None
            if up > 1:
                block = mvs[k][:, ::up, ::up]
            elif down > 1:
                block = mvs[k].repeat_interleave(down, 1).repeat_interleave(down, 2)
            y0, x0 = corner[0] * down // up, corner[1] * down // up
            d[:, y0 : y0 + block.shape[1], x0 : x0 + block.shape[2]] = block
            near = torch.rand(1, *self.size, generator=g) < 1 / 3
            d = torch.where(near, 0.8 * d, d)
            d[torch.rand(1, *self.size, generator=g) < 0.4] = 0.0  # no return there
            sweeps[view] = d
        return crops, ConsistentDepth(mvs, torch.zeros(2, 3, *crop), keep), _Sweeps(sweeps)

    def reference(self, crops, cons, sweeps, group, tol):
        """A loop over the members' crop pixels, the sweep resampled to the matching scale."""
        up, down = crops.scale.up, crops.scale.down
        ch, cw = crops.size
        checked, bad = torch.zeros_like(cons.keep), torch.zeros_like(cons.keep)
        for k, (i, (y0, x0)) in enumerate(zip(crops.members, crops.corners)):
            s = sweeps.depth[group[i]]
            for y in range(ch):
                for x in range(cw):
                    Y, X = y0 + y, x0 + x  # at the matching scale
                    if up > 1:
                        d = float(s[0, Y // up, X // up])
                    else:
                        b = s[0, Y * down : (Y + 1) * down, X * down : (X + 1) * down]
                        d = float(b[b > 0].mean()) if (b > 0).float().mean() >= 0.5 else 0.0
                    m = float(cons.depth[k, 0, y, x])
                    checked[k, 0, y, x] = bool(cons.keep[k, 0, y, x]) and d > 0
                    bad[k, 0, y, x] = bool(checked[k, 0, y, x]) and abs(m - d) > tol * d
        return checked, bad

    @pytest.mark.parametrize("scale", [MatchScale(), MatchScale(up=2), MatchScale(down=2)])
    def test_against_a_loop(self, scale):
        crops, cons, sweeps = self.case(scale)
        cfg = ReconstructConfig(max_lidar_error=0.1)
        got = lidar_check(sweeps, cons, crops, [7, 9], cfg)
        checked, bad = self.reference(crops, cons, sweeps, [7, 9], 0.1)
        assert torch.equal(got.checked, checked) and torch.equal(got.contradicted, bad)
        n_checked, n_bad = int(checked.sum()), int(bad.sum())
        assert 0 < n_bad < n_checked < int(cons.keep.sum())  # the case has every kind
        if scale == MatchScale():  # at one scale: exactly the pixels whose sweep is 20 % nearer
            assert 0.2 < n_bad / n_checked < 0.5

    def test_off_checks_nothing(self):
        crops, cons, sweeps = self.case(MatchScale())
        got = lidar_check(sweeps, cons, crops, [7, 9], ReconstructConfig(max_lidar_error=None))
        assert not got.checked.any() and not got.contradicted.any()
        loose = lidar_check(sweeps, cons, crops, [7, 9], ReconstructConfig(max_lidar_error=0.3))
        assert loose.checked.any() and not loose.contradicted.any()  # 20 % is within 30 %


class TestDepthPriors:
    @pytest.mark.parametrize("scale", [MatchScale(), MatchScale(up=2), MatchScale(down=2)])
    def test_against_a_loop(self, scale):
        g = torch.Generator().manual_seed(2)
        size = (12, 14)  # the scene's resolution
        up, down = scale.up, scale.down
        crop = (4 * up, 6 * up) if up > 1 else (4 // down, 6 // down)  # at the matching scale
        crops = crops_of(
            [0, 1], [(1 * up // down, 2 * up // down), (6 * up // down, 8 * up // down)], crop, scale
        )
        assert crops.size_lo == (4, 6)
        depth = 1.0 + torch.rand(2, 1, *crop, generator=g)
        normal = torch.nn.functional.normalize(torch.randn(2, 3, *crop, generator=g), dim=1)
        keep = torch.rand(2, 1, *crop, generator=g) > 0.3
        full_depth, full_normal = depth_priors(ConsistentDepth(depth, normal, keep), crops, size)
        assert len(full_depth) == len(full_normal) == 2
        for k, (y0, x0) in enumerate(crops.corners_lo):
            want_d, want_n = torch.zeros(1, *size), torch.zeros(3, *size)
            for y in range(4):
                for x in range(6):
                    if up > 1:  # the mean of the kept pixels of the block, if half of them are
                        sl = (k, slice(None), slice(y * up, (y + 1) * up), slice(x * up, (x + 1) * up))
                        kb = keep[sl][0]
                        if kb.float().mean() >= 0.5:
                            want_d[:, y0 + y, x0 + x] = depth[sl][:, kb].mean(-1)
                            want_n[:, y0 + y, x0 + x] = torch.nn.functional.normalize(
                                normal[sl][:, kb].mean(-1), dim=0
                            )
                    elif keep[k, 0, y // down, x // down]:  # the pixel of its block
                        want_d[:, y0 + y, x0 + x] = depth[k, :, y // down, x // down]
                        want_n[:, y0 + y, x0 + x] = normal[k, :, y // down, x // down]
            assert torch.allclose(full_depth[k], want_d, atol=1e-6)
            assert torch.allclose(full_normal[k], want_n, atol=1e-6)
            assert (full_depth[k] > 0).sum() > 0
