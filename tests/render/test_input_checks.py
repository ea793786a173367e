"""The rasterizers' input checks (:func:`vadgs.render.common.check_raster_inputs`): one host sync
for every value check together on valid inputs (a GPU waits at each), and on a bad input the same
error as each check alone, naming the first that fails."""

from __future__ import annotations

import pytest
import torch

from vadgs.render.common import check_raster_inputs


def _inputs(n=50, b=2, seed=0):
    g = torch.Generator().manual_seed(seed)
    w2c = torch.eye(4).repeat(b, 1, 1)
    K = torch.tensor([[30.0, 0, 16], [0, 30.0, 12], [0, 0, 1]]).repeat(b, 1, 1)
    return dict(
        means=torch.randn(n, 3, generator=g) + torch.tensor([0, 0, 5.0]),
        quats=torch.randn(n, 4, generator=g),
        scales=torch.rand(n, 3, generator=g) * 0.1,
        opacities=torch.rand(n, generator=g),
        colors=torch.rand(n, 3, generator=g),
        world_to_cam=w2c,
        K=K,
        background=torch.zeros(3),
    )


class _Reads:
    """Counts the reads of a tensor's value by the host (bool, int, float, item, tolist)."""

    NAMES = ("__bool__", "__int__", "__float__", "__index__", "item", "tolist")

    def __init__(self, monkeypatch):
        self.count = 0
        for name in self.NAMES:
            orig = getattr(torch.Tensor, name)

            def counted(t, *a, _orig=orig, **k):
                self.count += 1
                return _orig(t, *a, **k)

            monkeypatch.setattr(torch.Tensor, name, counted)


def test_valid_inputs_cost_one_host_read(monkeypatch):
    x = _inputs()
    reads = _Reads(monkeypatch)
    dims = check_raster_inputs(**x)
    assert dims["N"] == 50 and dims["B"] == 2
    assert reads.count == 1


@pytest.mark.parametrize(
    "change, message",
    [
        (
            lambda x: x["means"].__setitem__((3, 1), float("nan")),
            "means: expected finite values, got 1 non-finite",
        ),
        (
            lambda x: x["colors"].__setitem__((0, 0), float("inf")),
            "colors: expected finite values, got 1 non-finite",
        ),
        (lambda x: x["K"].__setitem__((1, 0, 0), 0.0), "K: expected positive focal lengths .* camera b=1"),
        (lambda x: x["quats"].__setitem__(7, 0.0), "quats: expected non-zero quaternions, got 1 of norm 0"),
        (lambda x: x["scales"].__setitem__((2, 2), -0.1), "scales: expected activated"),
        (lambda x: x["opacities"].__setitem__(4, 1.5), "opacities: expected activated opacities"),
        (lambda x: x["scales"].__setitem__((1, 0), 1e20), r"scales: expected < .* got max 1e\+20"),
        # two faults: the first check in order names its own
        (lambda x: (x["K"].__setitem__((0, 1, 1), -1.0), x["opacities"].__setitem__(0, -1.0)), "K: expected"),
    ],
)
def test_bad_inputs_name_the_first_failing_check(change, message):
    x = _inputs()
    change(x)
    with pytest.raises(ValueError, match=message):
        check_raster_inputs(**x)


def test_empty_model_passes():
    x = _inputs(n=0)
    assert check_raster_inputs(**x)["N"] == 0
