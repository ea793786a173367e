"""The ground of a scene (:mod:`vadgs.geometry.ground`): the row sample of :func:`sample_rows` against
its hash-threshold reference; :func:`ground_cells`: the cells move with the scene (issue 31), against
a naive reference in the scene's own ground frame, and the same cells in a turned, shifted, rescaled
and tilted copy of it."""

from __future__ import annotations

import math

import pytest
import torch

from vadgs.geometry import sample_rows
from vadgs.geometry.ground import ground_cells


@pytest.mark.parametrize("budget", [1, 7, 64, 1000, 10_000])
def test_row_sample_takes_rows_by_position(budget):
    g = torch.Generator().manual_seed(budget)
    chunks = [torch.rand(int(n), 3, generator=g) for n in torch.randint(0, 900, (12,), generator=g)]
    rows = torch.cat(chunks)
    got = sample_rows(iter(chunks), budget)
    # the reference: the largest threshold 2**32 / 2**k of the rows' hashes that keeps <= budget
    key = (torch.arange(rows.shape[0]) * 2654435761) % 2**32
    limit = 2**32
    while int((key < limit).sum()) > budget:
        limit //= 2
    assert torch.equal(got, rows[key < limit]) and got.shape[0] <= budget
    assert budget >= rows.shape[0] or got.shape[0] > budget // 4  # thinned by halves, not more
    assert sample_rows(iter([]), budget).shape == (0, 3)


def test_row_sample_does_not_alias_with_a_scan_pattern():
    """64 beams, one row each in turn: a stride of 64 would keep one beam; the sample keeps all."""
    beams = torch.arange(64).repeat(2000).double()[:, None].expand(-1, 3)
    got = sample_rows(beams.split(5000), 2000)
    counts = torch.bincount(got[:, 0].long(), minlength=64)
    assert 1000 < got.shape[0] <= 2000 and int(counts.min()) > 0.5 * float(counts.double().mean())


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
