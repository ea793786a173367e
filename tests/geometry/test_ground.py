"""The row sample of :func:`vadgs.geometry.ground.sample_rows` against its hash-threshold reference."""

from __future__ import annotations

import pytest
import torch

from vadgs.geometry import sample_rows


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
