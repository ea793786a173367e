"""Planar completion: RANSAC plane fit and the filling of a textureless hole in a flat region."""

import math

import pytest
import torch
from scipy import ndimage

from vadgs.geometry import backproject_depth, project_points
from vadgs.mvs import PlanarCompletionConfig, complete_planar, fit_plane_ransac

F, Z, B = 50.0, 2.0, 0.2  # focal, plane depth, baseline: disparity F * B / Z = 5 px


def _scene(hole_colour=(0.2, 0.4, 0.9)):
    g = torch.Generator().manual_seed(0)
    h, w = 40, 64
    K = torch.tensor([[F, 0, 31.5], [0, F, 19.5], [0, 0, 1]])
    image = torch.rand(3, h, w, generator=g)
    hole = torch.zeros(1, h, w, dtype=torch.bool)
    hole[:, 12:28, 20:40] = True
    image = torch.where(hole, torch.tensor(hole_colour)[:, None, None], image)  # textureless board
    src = torch.roll(image, shifts=-5, dims=-1)[None]  # camera moved by +B along x
    src_w2c = torch.eye(4)[None].clone()
    src_w2c[0, 0, 3] = -B
    depth = torch.full((1, h, w), Z)
    return image, K, hole, src, src_w2c, depth


def _batch(*cases):
    """One view's arguments of several cases (as :func:`_complete_planar_naive` takes them) stacked."""
    return [torch.stack([c[i] for c in cases]) for i in range(len(cases[0]))]


def _one(*args, **kwargs):
    """:func:`complete_planar` of one view: its unbatched arguments and outputs."""
    n = 10
    out, normal, added = complete_planar(*_batch(args[:n]), *args[n:], **kwargs)
    return out[0], normal[0], added[0]


def _complete_planar_naive(
    depth: torch.Tensor,
    valid: torch.Tensor,
    region: torch.Tensor,
    image: torch.Tensor,
    K: torch.Tensor,
    cam_to_world: torch.Tensor,
    src_images: torch.Tensor,
    src_regions: torch.Tensor,
    src_K: torch.Tensor,
    src_world_to_cam: torch.Tensor,
    config: PlanarCompletionConfig | None = None,
    generator: torch.Generator | None = None,
    normal: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """One view by pixel lists: the reference of :func:`complete_planar` (the implementation it replaced).

    RANSAC by :func:`fit_plane_ransac`, the gap by scipy's distance transform, the colour test by
    indexing each source at each candidate's projection.
    """
    cfg = config or PlanarCompletionConfig()
    sd = dict(zip(("V", "_", "Hs", "Ws"), src_images.shape))
    none = torch.zeros_like(valid)
    zero_n = torch.zeros(3, dtype=depth.dtype, device=depth.device)
    if sd["V"] == 0:
        return depth, zero_n, none
    good = valid & region & (depth > 0)
    gy, gx = torch.nonzero(good[0], as_tuple=True)  # one read: the consistent pixels, row-major
    if gy.numel() < cfg.min_pixels:
        return depth, zero_n, none
    pts = backproject_depth(depth[None], K[None])[0]  # (3, H, W) camera frame
    p = pts[:, gy, gx].T
    nrm, angle = None, 90.0  # the angle is unused without normals
    if normal is not None and cfg.max_normal_angle is not None:
        nrm = torch.nn.functional.normalize(normal[:, gy, gx].T, dim=-1)
        angle = cfg.max_normal_angle
    fit = fit_plane_ransac(p, cfg.rel_threshold * p[:, 2], cfg.iterations, generator, nrm, angle)
    if fit is None:
        return depth, zero_n, none
    inf = torch.full_like(p[:, 2], math.inf)
    ratio, off, z_min, z_max = torch.stack(
        [
            fit.inliers.float().mean().double(),
            fit.offset.double(),
            torch.where(fit.inliers, p[:, 2], inf).min().double(),
            torch.where(fit.inliers, p[:, 2], -inf).max().double(),
        ]
    ).tolist()  # one read (float64 holds each value exactly)
    if ratio < cfg.min_inlier_ratio:
        return depth, zero_n, none
    normal, offset = fit.normal, fit.offset
    if off < 0:  # the camera (origin) on the positive side: the normal faces it
        normal, offset = -normal, -offset
    # candidates: empty region pixels near an inlier
    inl = torch.zeros_like(good[0])
    inl[gy, gx] = fit.inliers
    near = torch.from_numpy(ndimage.distance_transform_edt(~inl.numpy())) <= cfg.max_gap
    cand = region & ~good & near[None]
    ys, xs = torch.nonzero(cand[0], as_tuple=True)  # one read
    if ys.numel() == 0:
        return depth, normal, none
    pix = torch.stack([xs, ys, torch.ones_like(xs)], -1).to(depth)
    rays = pix @ torch.linalg.inv(K).T
    den = rays @ normal
    z = -offset / torch.where(den.abs() > 1e-9, den, torch.full_like(den, 1e-9))
    ok = (z > 0.5 * z_min) & (z < 2.0 * z_max)
    cam = rays * z[:, None]
    world = cam @ cam_to_world[:3, :3].T + cam_to_world[:3, 3]
    colour = image[:, ys, xs].T  # (P, 3)
    v = sd["V"]
    uv, zs = project_points(world[None].expand(v, -1, -1), src_K, src_world_to_cam)
    qx, qy = uv[..., 0].round().long(), uv[..., 1].round().long()
    inside = (zs > 0) & (qx >= 0) & (qx < sd["Ws"]) & (qy >= 0) & (qy < sd["Hs"])
    qx, qy = qx.clamp(0, sd["Ws"] - 1), qy.clamp(0, sd["Hs"] - 1)
    views = torch.arange(v, device=qx.device)[:, None]
    sc = src_images.permute(0, 2, 3, 1)[views, qy, qx]  # (V, P, 3): each view's colour there
    match = (sc - colour).abs().mean(-1) <= cfg.color_tolerance
    agree = (inside & src_regions[views, 0, qy, qx] & match).long().sum(0)
    keep = ok & (agree >= cfg.min_views)
    out = depth.clone()
    added = torch.zeros_like(valid)
    out[0, ys, xs] = torch.where(keep, z, out[0, ys, xs])
    added[0, ys, xs] = keep
    return out, normal, added


def test_fit_plane_ransac_ignores_outliers():
    g = torch.Generator().manual_seed(1)
    xy = torch.rand(300, 2, generator=g) * 4 - 2
    pts = torch.cat([xy, (0.3 * xy[:, :1] - 0.2 * xy[:, 1:] + 5)], dim=1)
    pts[:90] += torch.randn(90, 3, generator=g)  # 30 % outliers
    fit = fit_plane_ransac(pts, 0.01, generator=g)
    n = fit.normal / -fit.normal[2]
    assert torch.allclose(n[:2], torch.tensor([0.3, -0.2]), atol=1e-4)
    assert fit.inliers[90:].all() and fit.inliers[:90].float().mean() < 0.1
    assert fit_plane_ransac(pts[:2], 0.01) is None


def test_fills_a_textureless_hole_of_a_plane_with_the_true_depth():
    image, K, hole, src, src_w2c, depth = _scene()
    region = torch.ones_like(hole)
    region[:, :, :6] = False  # the source does not see the left border
    valid = region & ~hole  # PatchMatch left the flat board empty
    out, normal, added = _one(
        torch.where(valid, depth, 0), valid, region, image, K, torch.eye(4),
        src, torch.ones_like(src[:, :1], dtype=torch.bool), K[None], src_w2c,
    )  # fmt: skip
    inner = hole.clone()
    inner[:, :, 20:26] = False  # the source sees the hole's left part on texture (x - 5)
    assert added[inner].float().mean() > 0.95
    assert torch.allclose(out[added], torch.full_like(out[added], Z), rtol=1e-3)
    assert torch.allclose(normal, torch.tensor([0.0, 0.0, -1.0]), atol=1e-3)  # faces the camera
    assert not added[~region].any()


def test_a_colour_mismatch_in_every_view_blocks_the_fill():
    image, K, hole, src, src_w2c, depth = _scene()
    src = src.clone()
    src[:, :, 12:28] = 1 - src[:, :, 12:28]  # an occluder of another colour in the source
    region = torch.ones_like(hole)
    valid = ~hole
    _, _, added = _one(
        torch.where(valid, depth, 0), valid, region, image, K, torch.eye(4),
        src, torch.ones_like(src[:, :1], dtype=torch.bool), K[None], src_w2c,
    )  # fmt: skip
    assert not added.any()


def test_a_non_planar_region_is_left_alone():
    image, K, hole, src, src_w2c, depth = _scene()
    g = torch.Generator().manual_seed(2)
    bumpy = depth * (1 + 0.3 * torch.rand(depth.shape, generator=g))
    valid = ~hole
    _, normal, added = _one(
        torch.where(valid, bumpy, 0), valid, torch.ones_like(hole), image, K, torch.eye(4),
        src, torch.ones_like(src[:, :1], dtype=torch.bool), K[None], src_w2c,
        PlanarCompletionConfig(min_inlier_ratio=0.6),
    )  # fmt: skip
    assert not added.any() and (normal == 0).all()


def test_bad_shapes_name_the_argument():
    image, K, hole, src, src_w2c, depth = _scene()
    with pytest.raises(ValueError, match="src_regions"):
        _one(
            depth, ~hole, ~hole, image, K, torch.eye(4), src, torch.ones(2, 1, 3, 3, dtype=torch.bool),
            K[None], src_w2c,
        )  # fmt: skip


def test_normals_veto_inliers_that_disagree():
    g = torch.Generator().manual_seed(3)
    xy = torch.rand(100, 2, generator=g)
    pts = torch.cat([xy, torch.full((100, 1), 2.0)], dim=1)  # the plane z = 2
    up = torch.tensor([[0.0, 0.0, 1.0]]).expand(100, 3)
    side = torch.tensor([[1.0, 0.0, 0.0]]).expand(100, 3)
    assert fit_plane_ransac(pts, 0.01, generator=g, normals=up).inliers.all()
    assert not fit_plane_ransac(pts, 0.01, generator=g, normals=side, max_angle=30.0).inliers.any()


@pytest.mark.parametrize("max_gap", [0.0, 1.0, 2.5, 8.0])
def test_near_is_scipys_distance_transform_within_the_gap(max_gap):
    """The device dilation that replaced scipy's ``distance_transform_edt`` through ``.cpu()``."""
    from scipy import ndimage

    from vadgs.mvs.planar import near_pixels

    g = torch.Generator().manual_seed(int(max_gap * 10))
    for density in (0.002, 0.02, 0.2):
        mask = torch.rand(37, 53, generator=g) < density
        mask[0, 0] = True  # at least one set pixel (the transform's zeros)
        edt = torch.from_numpy(ndimage.distance_transform_edt(~mask.numpy()))
        assert torch.equal(near_pixels(mask[None], max_gap)[0], edt <= max_gap)


def test_batch_fills_as_each_case_alone():
    """Three views at once (a hole to fill, a colour mismatch, a bumpy region), as the naive reference."""
    image, K, hole, src, src_w2c, depth = _scene()
    region = torch.ones_like(hole)
    region[:, :, :6] = False
    valid = region & ~hole
    ones = torch.ones_like(src[:, :1], dtype=torch.bool)
    fill = (torch.where(valid, depth, 0), valid, region, image, K, torch.eye(4), src, ones, K[None], src_w2c)
    bad_src = src.clone()
    bad_src[:, :, 12:28] = 1 - bad_src[:, :, 12:28]
    full = torch.ones_like(hole)
    blocked = (
        torch.where(~hole, depth, 0),
        ~hole,
        full,
        image,
        K,
        torch.eye(4),
        bad_src,
        ones,
        K[None],
        src_w2c,
    )
    bumpy = depth * (1 + 0.3 * torch.rand(depth.shape, generator=torch.Generator().manual_seed(2)))
    rough = (torch.where(~hole, bumpy, 0), ~hole, full, image, K, torch.eye(4), src, ones, K[None], src_w2c)
    g = torch.Generator().manual_seed(0)
    out, normal, added = complete_planar(*_batch(fill, blocked, rough), generator=g)
    for k, case in enumerate((fill, blocked, rough)):
        _, n1, a1 = _complete_planar_naive(*case, generator=torch.Generator().manual_seed(0))
        union = (added[k] | a1).sum()
        if union:
            assert (added[k] & a1).sum() / union > 0.95, k  # the same pixels filled
            assert torch.allclose(out[k][added[k]], torch.full_like(out[k][added[k]], Z), rtol=1e-3)
        else:
            assert not added[k].any()
        assert torch.allclose(normal[k], n1, atol=1e-3), k
    assert added[0].sum() > 200 and not added[1].any() and not added[2].any()
    assert torch.equal(out[1], fill[0] * 0 + blocked[0]) and torch.equal(out[2], rough[0])


def test_batch_reads_the_device_once():
    """One host read (the most consistent pixels of a view), value checks off as in an event."""
    from vadgs.checks import checking

    from ..launch_count import LaunchCounter

    image, K, hole, src, src_w2c, depth = _scene()
    valid = ~hole
    ones = torch.ones_like(src[:, :1], dtype=torch.bool)
    case = (
        torch.where(valid, depth, 0),
        valid,
        torch.ones_like(hole),
        image,
        K,
        torch.eye(4),
        src,
        ones,
        K[None],
        src_w2c,
    )
    with checking(False), LaunchCounter() as c:
        complete_planar(*_batch(case, case, case), generator=torch.Generator().manual_seed(0))
    assert c.host_reads == 1
