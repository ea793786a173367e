"""fill_holes_scanline against a per-pixel loop."""

import pytest
import torch

from vadgs.mvs import fill_holes_scanline


def _loop(depth, valid, keep):
    out = depth.clone()
    b, _, h, w = depth.shape
    for i in range(b):
        for y in range(h):
            for x in range(w):
                if valid[i, 0, y, x]:
                    continue
                left = [depth[i, 0, y, k] for k in range(x - 1, -1, -1) if valid[i, 0, y, k]][:1]
                right = [depth[i, 0, y, k] for k in range(x + 1, w) if valid[i, 0, y, k]][:1]
                cands = left + right
                if not cands:
                    out[i, 0, y, x] = 0
                else:
                    out[i, 0, y, x] = max(cands) if keep == "far" else min(cands)
    return out


@pytest.mark.parametrize("keep", ["far", "near"])
def test_matches_a_loop(keep):
    g = torch.Generator().manual_seed(0)
    depth = torch.rand(2, 1, 7, 13, generator=g) * 10 + 1
    valid = torch.rand(2, 1, 7, 13, generator=g) > 0.6
    valid[0, 0, 3] = False  # a row without any valid pixel
    out = fill_holes_scanline(depth, valid, keep)
    assert torch.equal(out, _loop(depth, valid, keep))
    assert (out[0, 0, 3] == 0).all()


def test_bad_input():
    with pytest.raises(ValueError, match="valid"):
        fill_holes_scanline(torch.ones(1, 1, 4, 5), torch.ones(1, 1, 4, 6, dtype=torch.bool))
    with pytest.raises(ValueError, match="keep"):
        fill_holes_scanline(torch.ones(1, 1, 4, 5), torch.ones(1, 1, 4, 5, dtype=torch.bool), keep="mean")
