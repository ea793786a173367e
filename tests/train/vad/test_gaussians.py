"""The Gaussians of a reconstruction (:func:`vadgs.train.vad.gaussians.flat_gaussians`): flat discs
on the MVS points, their normal the MVS normal, their size the points' spacing, in the model's own
layout (vadgs's or gsplat's), against hand-computed values."""

from __future__ import annotations

import math

import torch

from vadgs.geometry import quaternion_to_rotation
from vadgs.geometry.rotation import normals_to_quats
from vadgs.train.strategy import ops
from vadgs.train.vad import InstanceReconstruction, flat_gaussians

C0 = 0.28209479177387814  # the SH band-0 constant


# -- flat_gaussians ----------------------------------------------------------------------------------


def _fused(dtype=torch.float32) -> InstanceReconstruction:
    """Three fused points: normals +z, +x and a tilted one; spacing 0.1, 0.2 and 0 (clamped)."""
    return InstanceReconstruction(
        points=torch.tensor([[1.0, 2.0, 3.0], [4.0, 5.0, 6.0], [7.0, 8.0, 9.0]], dtype=dtype),
        normals=torch.tensor([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 0.6, 0.8]], dtype=dtype),
        colors=torch.tensor([[0.5, 0.25, 1.0], [0.0, 0.75, 0.5], [0.1, 0.2, 0.3]], dtype=dtype),
        spacing=torch.tensor([0.1, 0.2, 0.0], dtype=dtype),
        track=None,
        views=[0],
        depth=[],
        normal=[],
        reason="ok",
    )


class TestFlatGaussians:
    def _check_geometry(self, new, means, quats, scales, opacities, rows, flatness=0.2, opacity=0.3):
        rec = _fused()
        assert torch.equal(new[means], rec.points[rows])
        r = quaternion_to_rotation(new[quats])
        torch.testing.assert_close(r[:, :, 2], rec.normals[rows])  # the disc's normal: the MVS normal
        torch.testing.assert_close(r.transpose(1, 2) @ r, torch.eye(3).expand(len(rows), 3, 3))
        width = [max(float(rec.spacing[k]), 1e-4) for k in rows]
        expect = [[math.log(w), math.log(w), math.log(w * flatness)] for w in width]
        torch.testing.assert_close(new[scales], torch.tensor(expect))
        torch.testing.assert_close(
            new[opacities], torch.full((len(rows),), math.log(opacity / (1 - opacity)))
        )

    def test_vadgs_layout(self):
        params = {
            "means": torch.zeros(2, 3),
            "quats": torch.zeros(2, 4),
            "log_scales": torch.zeros(2, 3),
            "opacity_logits": torch.zeros(2),
            "sh_dc": torch.zeros(2, 1, 3),
            "sh_rest": torch.zeros(2, 8, 3),
            "node_ids": torch.zeros(2, dtype=torch.int64),
            "provenance": torch.zeros(2, dtype=torch.int64),
        }
        new = flat_gaussians(params, _fused(), None, new_opacity=0.3, flatness=0.2, event=4, node=2)
        assert set(new) == set(params)
        assert new["node_ids"].tolist() == [2, 2, 2] and new["node_ids"].dtype == torch.int64
        assert flat_gaussians(params, _fused())["node_ids"].tolist() == [-1, -1, -1]  # static by default
        self._check_geometry(new, "means", "quats", "log_scales", "opacity_logits", [0, 1, 2])
        expect_dc = [[[(0.5 - 0.5) / C0, (0.25 - 0.5) / C0, (1.0 - 0.5) / C0]]]
        torch.testing.assert_close(new["sh_dc"][:1], torch.tensor(expect_dc))
        assert torch.equal(new["sh_rest"], torch.zeros(3, 8, 3))
        assert new["provenance"].tolist() == [4, 4, 4] and new["provenance"].dtype == torch.int64

    def test_gsplat_colors_layout(self):
        """gsplat's appearance layout: ``colors`` (N, 3) get the logit of the MVS colour, unknown
        entries (``features``) zeros of their trailing shape and dtype; ``keep`` selects points."""
        params = {
            "means": torch.zeros(2, 3, dtype=torch.float64),
            "quats": torch.zeros(2, 4, dtype=torch.float64),
            "scales": torch.zeros(2, 3, dtype=torch.float64),
            "opacities": torch.zeros(2, dtype=torch.float64),
            "features": torch.zeros(2, 32, dtype=torch.float16),
            "colors": torch.zeros(2, 3, dtype=torch.float64),
        }
        keep = torch.tensor([True, False, True])
        new = flat_gaussians(params, _fused(), keep, new_opacity=0.3, flatness=0.5)
        assert set(new) == set(params)
        assert all(new[k].dtype == params[k].dtype for k in params)
        new32 = {k: v.float() for k, v in new.items()}
        self._check_geometry(new32, "means", "quats", "scales", "opacities", [0, 2], flatness=0.5)
        eps = 1e-4
        expect = [
            [math.log(c / (1 - c)) for c in (0.5, 0.25, 1 - eps)],
            [math.log(c / (1 - c)) for c in (0.1, 0.2, 0.3)],
        ]
        torch.testing.assert_close(
            new["colors"], torch.tensor(expect, dtype=torch.float64), rtol=1e-5, atol=1e-4
        )
        assert torch.equal(new["features"], torch.zeros(2, 32, dtype=torch.float16))
        assert "sh0" not in new and ops.param_names(params).sh_dc is None

    def test_normals_to_quats_is_a_rotation_onto_the_normal(self):
        n = torch.nn.functional.normalize(
            torch.randn(50, 3, generator=torch.Generator().manual_seed(1)), dim=-1
        )
        r = quaternion_to_rotation(normals_to_quats(n))
        torch.testing.assert_close(r[:, :, 2], n, atol=1e-5, rtol=0)
        torch.testing.assert_close(torch.linalg.det(r), torch.ones(50), atol=1e-5, rtol=0)
