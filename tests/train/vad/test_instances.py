"""Derived instances of a scene without an instance map (:mod:`vadgs.train.vad.instances`).

:func:`ground_cells`: the cells move with the scene (issue 31), against a naive reference in the
scene's own ground frame, and the same cells in a turned, shifted, rescaled and tilted copy of it.
:func:`derive_instance_map` against a naive, pixel-by-pixel reference: ground cells of the voxels,
grown into the pixels without a voxel, cut to the view's own area, and the moving objects'
projected boxes painted far to near."""

from __future__ import annotations

import itertools
import math
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from scipy.spatial import ConvexHull

from vadgs.train.vad.instances import derive_instance_map, ground_cells
from vadgs.train.vad.lengths import scene_lengths


def _rot(axis: str, angle: float) -> torch.Tensor:
    c, s = math.cos(angle), math.sin(angle)
    i, j = {"x": (1, 2), "y": (2, 0), "z": (0, 1)}[axis]
    out = torch.eye(3, dtype=torch.float64)
    out[i, i], out[i, j], out[j, i], out[j, j] = c, -s, s, c
    return out


def _street(n: int = 4000):
    """Points of a street 60 m long along the world's x, 12 m wide, up to 8 m high; level cameras
    driving along it (OpenCV axes, z up)."""
    g = torch.Generator().manual_seed(3)
    size = torch.tensor([60.0, 12.0, 8.0], dtype=torch.float64)
    pts = torch.rand(n, 3, generator=g, dtype=torch.float64) * size
    pts[:, :2] -= torch.tensor([10.0, 6.0], dtype=torch.float64)
    c2w = torch.eye(4, dtype=torch.float64).repeat(8, 1, 1)
    forward = torch.tensor([[0.0, 1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]], dtype=torch.float64)
    for k in range(8):  # x right, y down, z forward; some pitched down, some turned
        c2w[k, :3, :3] = _rot("z", 0.3 * (k % 3 - 1)) @ forward.T @ _rot("x", 0.1 * (k % 2))
        c2w[k, :3, 3] = torch.tensor([5.0 * k, 0.0, 1.5], dtype=torch.float64)
    return pts, c2w


def test_against_the_ground_frame_reference():
    pts, c2w = _street()
    cells = ground_cells(pts, c2w, 10.0)
    # reference: the ground frame by numpy's SVD of the points' x, y (the cameras are level, z up)
    import numpy as np

    xy = pts[:, :2].numpy()
    _, _, vt = np.linalg.svd(xy - xy.mean(0), full_matrices=False)
    uv = torch.from_numpy(xy @ vt.T)
    uv = uv - torch.from_numpy(np.median(uv.numpy(), axis=0))
    ij = torch.floor(uv / 10.0 + 0.5).long()
    keys = [tuple(k) for k in ij.tolist()]
    # the same partition (labels may differ): points share a cell in one iff in the other
    first: dict[int, tuple] = {}
    for c, k in zip(cells.tolist(), keys):
        assert first.setdefault(c, k) == k
    assert len(first) == len(set(keys)) == 7 * 3  # 60 m / 10 (a cell centred on the median) x 12 m / 10
    counts = torch.bincount(cells)
    assert (counts[:-1] >= counts[1:]).all()  # numbered most points first


@pytest.mark.parametrize(
    "turn, shift, scale, tilt",
    [
        (0.7, (3.0, -2.0, 1.0), 1 / 20, 0.0),
        (2.5, (-40.0, 7.0, 0.0), 3.0, 0.0),
        (1.2, (0.0, 0.0, 5.0), 0.5, 0.4),
    ],
)
def test_same_cells_in_a_moved_copy(turn, shift, scale, tilt):
    """Turned about the up, shifted, rescaled (cell size with it), and tilted (the world's z no
    longer up: the cameras' up decides)."""
    pts, c2w = _street()
    R = _rot("x", tilt) @ _rot("z", turn)
    t = torch.tensor(shift, dtype=torch.float64)
    moved = c2w.clone()
    moved[:, :3, :3] = R @ c2w[:, :3, :3]
    moved[:, :3, 3] = scale * (c2w[:, :3, 3] @ R.T) + t
    a = ground_cells(pts, c2w, 10.0)
    b = ground_cells(scale * (pts @ R.T) + t, moved, 10.0 * scale)
    assert torch.equal(a, b)


def test_world_axis_cells_would_differ():
    """The reason for the frame: square cells on the world's axes cut a turned copy elsewhere."""
    pts, _ = _street()
    R = _rot("z", 0.7)
    naive_a = torch.unique(torch.floor(pts[:, :2] / 10.0), dim=0, return_inverse=True)[1]
    naive_b = torch.unique(torch.floor((pts @ R.T)[:, :2] / 10.0), dim=0, return_inverse=True)[1]
    same = (naive_a[:, None] == naive_a[None]) == (naive_b[:, None] == naive_b[None])
    assert same.float().mean() < 0.95  # many point pairs change from together to apart


def test_degenerate_inputs_and_bad_cell_size():
    pts, c2w = _street(10)
    assert ground_cells(pts[:0], c2w, 10.0).shape == (0,)
    assert ground_cells(pts[:1], c2w, 10.0).tolist() == [0]
    assert ground_cells(pts, c2w[:0], 10.0).shape == (10,)  # no cameras: the world's z is up
    with pytest.raises(ValueError, match=r"cell_size: expected > 0, got -1"):
        ground_cells(pts, c2w, -1.0)


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
