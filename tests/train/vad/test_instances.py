"""Derived instances of a scene without an instance map (:mod:`vadgs.train.vad.instances`).

:func:`derive_instance_map` against a naive, pixel-by-pixel reference: ground cells of the voxels,
grown into the pixels without a voxel, cut to the view's own area, and the moving objects'
projected boxes painted far to near."""

from __future__ import annotations

import itertools
import math
from types import SimpleNamespace

import numpy as np
import torch
from scipy.spatial import ConvexHull

from vadgs.train.vad.instances import derive_instance_map
from vadgs.train.vad.lengths import scene_lengths

H, W = 24, 32


K = torch.tensor([[20.0, 0.0, 15.3], [0.0, 20.0, 11.7], [0.0, 0.0, 1.0]])


def _box(center, half):
    """``(8, 3)`` corners of an axis-aligned box in its object frame, centred at ``center``."""
    c, h = torch.tensor(center), torch.tensor(half)
    return torch.tensor(list(itertools.product((-1.0, 1.0), repeat=3))) * h + c


def _track(position, valid=True):
    o2w = torch.eye(4)
    o2w[:3, 3] = torch.tensor(position)
    return SimpleNamespace(valid=torch.tensor([valid]), object_to_world=o2w[None])


def _index(vox, cells, grow, tracks=None, boxes=None, own=(H, W)):
    """What ``derive_instance_map`` reads of a :class:`VisibilityIndex` (camera at the origin)."""
    valid = torch.zeros(H, W, dtype=torch.bool)
    valid[: own[0], : own[1]] = True
    return SimpleNamespace(
        inputs=SimpleNamespace(frame_position=lambda view: 0, tracks=tracks or {}),
        voxel_raster=lambda view: (None, vox),
        cell_ids=lambda: cells,
        grow=grow,
        camera=lambda view: SimpleNamespace(K=K[None], world_to_cam=torch.eye(4)[None]),
        valid=lambda view: valid,
        scene_depth=10.0,
        box_corners=lambda tid: boxes[tid],
        size=lambda view: (H, W),
    )


def _naive(index) -> tuple[np.ndarray, np.ndarray]:
    """The map, and per pixel whether its value is certain (not on a box edge, not a nearest-pixel
    tie between labels): those are the pixels compared."""
    _, vox = index.voxel_raster(0)
    cells = index.cell_ids()
    lab = np.zeros((H, W), dtype=np.int64)
    for y, x in itertools.product(range(H), range(W)):
        if vox[y, x] >= 0:
            lab[y, x] = int(cells[vox[y, x]])
    certain = np.ones((H, W), dtype=bool)
    grown = lab.copy()
    labelled = [(y, x) for y, x in itertools.product(range(H), range(W)) if lab[y, x] > 0]
    for y, x in itertools.product(range(H), range(W)):
        if lab[y, x] > 0 or not labelled:
            continue
        d2 = {(yy, xx): (yy - y) ** 2 + (xx - x) ** 2 for yy, xx in labelled}
        best = min(d2.values())
        if math.sqrt(best) <= index.grow:  # the nearest labelled pixel's id
            near = {int(lab[p]) for p, d in d2.items() if d == best}
            grown[y, x] = min(near)
            certain[y, x] = len(near) == 1
    lab = np.where(index.valid(0).numpy(), grown, 0)
    painted = []
    for tid, t in index.inputs.tracks.items():
        if not bool(t.valid[0]):
            continue
        world = index.box_corners(tid) + t.object_to_world[0, :3, 3]
        z = world[:, 2]
        if bool((z < scene_lengths(10.0)["box_near"]).any()):
            continue
        uv = (world[:, :2] / z[:, None]) * K[[0, 1], [0, 1]] + K[:2, 2]
        painted.append((float(z.mean()), tid, ConvexHull(uv.numpy()).equations))
    for _, tid, eq in sorted(painted, reverse=True):  # far first
        for y, x in itertools.product(range(H), range(W)):
            side = eq[:, :2] @ np.array([x, y]) + eq[:, 2]  # <= 0 on every face: inside
            if side.max() < -1e-3:
                lab[y, x] = tid
            elif side.max() <= 1e-3:
                certain[y, x] = False
    return lab, certain


def _compare(index) -> np.ndarray:
    got = derive_instance_map(index, 0).numpy()
    expect, certain = _naive(index)
    assert got.shape == (H, W) and got.dtype == np.int64
    assert certain.mean() > 0.8
    np.testing.assert_array_equal(got[certain], expect[certain])
    return got


class TestDeriveInstanceMap:
    def test_cells_and_growth_against_naive(self):
        g = torch.Generator().manual_seed(0)
        vox = torch.full((H, W), -1, dtype=torch.int64)
        vox[3:9, 4:12] = torch.randint(0, 5, (6, 8), generator=g)  # two blobs of voxels
        vox[15:20, 20:28] = torch.randint(5, 9, (5, 8), generator=g)
        vox[5, 6] = -1  # a hole inside a blob
        cells = torch.tensor([11, 11, 12, 12, 12, 30, 30, 31, 31])
        for grow in (0, 2, 6):
            got = _compare(_index(vox, cells, grow))
            if grow == 0:  # only the voxels' own pixels
                assert set(np.unique(got[vox.numpy() < 0])) == {0}
        got = _compare(_index(vox, cells, 6, own=(20, 26)))  # a smaller view, padded: nothing grows there
        assert (got[20:] == 0).all() and (got[:, 26:] == 0).all()

    def test_no_voxel_in_view(self):
        vox = torch.full((H, W), -1, dtype=torch.int64)
        assert (derive_instance_map(_index(vox, torch.tensor([5]), 6), 0) == 0).all()

    def test_no_static_voxel_in_the_scene(self):
        """An empty static grid (every point on a moving object): no cells; a box is still painted."""
        vox = torch.full((H, W), -1, dtype=torch.int64)
        empty = torch.zeros(0, dtype=torch.int64)
        assert (derive_instance_map(_index(vox, empty, 6), 0) == 0).all()
        tracks, boxes = {7: _track((0.0, 0.0, 20.0))}, {7: _box((0.0, 0.0, 0.0), 2.0)}
        got = _compare(_index(vox, empty, 6, tracks=tracks, boxes=boxes))
        assert set(np.unique(got)) == {0, 7}

    def test_boxes_far_to_near_against_naive(self):
        """Tracks' boxes painted over the cells, the near one over the far one; a track without a
        pose at the frame and a box across the image plane are not painted."""
        vox = torch.zeros(H, W, dtype=torch.int64)  # every pixel on voxel 0: cell 50
        cells = torch.tensor([50])
        tracks = {
            7: _track([0.3, 0.2, 8.0]),  # far, large
            3: _track([-0.9, -0.5, 4.0]),  # near, partly over 7
            4: _track([0.0, 0.0, 6.0], valid=False),  # no pose at the view's frame
            9: _track([0.0, 0.0, 0.5]),  # reaches behind the camera
        }
        boxes = {
            7: _box([0.0, 0.0, 0.0], [2.0, 1.5, 1.0]),
            3: _box([0.0, 0.0, 0.0], [0.6, 0.5, 0.4]),
            4: _box([0.0, 0.0, 0.0], [5.0, 5.0, 1.0]),
            9: _box([0.0, 0.0, 0.0], [1.0, 1.0, 1.0]),
        }
        got = _compare(_index(vox, cells, 0, tracks, boxes))
        assert set(np.unique(got)) == {3, 7, 50}
        yx3 = np.argwhere(got == 3)
        assert len(yx3) > 0 and (got[tuple(yx3.T)] == 3).all()
