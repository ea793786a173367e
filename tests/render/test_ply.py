from __future__ import annotations

import numpy as np
import pytest
import torch

from vadgs.render import load_ply, rgb_to_sh, save_ply


def _gaussians(n=50, k=16, seed=0):
    g = torch.Generator().manual_seed(seed)
    return (
        torch.randn(n, 3, generator=g),
        torch.randn(n, 4, generator=g),
        torch.rand(n, 3, generator=g) * 0.5 + 1e-3,
        torch.rand(n, generator=g) * 0.98 + 0.01,
        torch.randn(n, k, 3, generator=g),
    )


class TestPly:
    @pytest.mark.parametrize("k", [1, 4, 16])
    def test_round_trip(self, tmp_path, k):
        means, quats, scales, opac, sh = _gaussians(k=k)
        save_ply(tmp_path / "g.ply", means, quats, scales, opac, sh)
        g = load_ply(tmp_path / "g.ply")
        torch.testing.assert_close(g.means, means)
        torch.testing.assert_close(g.quats, quats)
        torch.testing.assert_close(g.scales, scales, rtol=1e-5, atol=1e-7)
        torch.testing.assert_close(g.opacities, opac, rtol=1e-5, atol=1e-6)
        torch.testing.assert_close(g.sh, sh)

    def test_layout_matches_3dgs(self, tmp_path):
        # Property order and the channel-major f_rest of the reference implementation.
        means, quats, scales, opac, sh = _gaussians(n=3, k=4)
        save_ply(tmp_path / "g.ply", means, quats, scales, opac, sh)
        raw = (tmp_path / "g.ply").read_bytes()
        head, body = raw.split(b"end_header\n")
        props = [line.split()[-1].decode() for line in head.splitlines() if line.startswith(b"property")]
        assert props[:9] == ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
        assert props[9:18] == [f"f_rest_{i}" for i in range(9)]
        assert props[18:] == ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
        arr = np.frombuffer(body, dtype="<f4").reshape(3, len(props))
        np.testing.assert_allclose(arr[:, 9:12], sh[:, 1:, 0].numpy(), rtol=1e-6)  # red first
        np.testing.assert_allclose(arr[:, 18], torch.logit(opac).numpy(), rtol=1e-5)
        np.testing.assert_allclose(arr[:, 19:22], scales.log().numpy(), rtol=1e-5)

    def test_rgb_colors(self, tmp_path):
        means, quats, scales, opac, _ = _gaussians(n=4)
        rgb = torch.rand(4, 3)
        save_ply(tmp_path / "g.ply", means, quats, scales, opac, rgb)
        torch.testing.assert_close(load_ply(tmp_path / "g.ply").sh[:, 0], rgb_to_sh(rgb))

    def test_exception(self, tmp_path):
        means, quats, scales, opac, sh = _gaussians(n=4, k=4)
        with pytest.raises(ValueError, match="scales"):
            save_ply(tmp_path / "g.ply", means, quats, scales[:3], opac, sh)
        with pytest.raises(ValueError, match="means: expected finite"):
            save_ply(tmp_path / "g.ply", means * float("inf"), quats, scales, opac, sh)
        (tmp_path / "bad.ply").write_bytes(b"hello")
        with pytest.raises(ValueError, match="not a PLY"):
            load_ply(tmp_path / "bad.ply")
        (tmp_path / "mesh.ply").write_bytes(
            b"ply\nformat binary_little_endian 1.0\nelement vertex 1\nproperty float x\nproperty float y\n"
            b"property float z\nend_header\n" + np.zeros(3, "<f4").tobytes()
        )
        with pytest.raises(ValueError, match="missing vertex properties"):
            load_ply(tmp_path / "mesh.ply")

    def test_empty(self, tmp_path):
        z = torch.zeros(0, 3)
        save_ply(tmp_path / "e.ply", z, torch.zeros(0, 4), z, torch.zeros(0), z)
        g = load_ply(tmp_path / "e.ply")
        assert g.means.shape == (0, 3) and g.sh.shape == (0, 1, 3)


class TestPlyFaults:
    """Reliability trial (issue 17): one PLY reader/writer with validated headers, atomic writes."""

    def _file(self, tmp_path, n=4, k=4):
        means, quats, scales, opac, sh = _gaussians(n=n, k=k)
        save_ply(tmp_path / "g.ply", means, quats, scales, opac, sh)
        return tmp_path / "g.ply"

    def test_truncated(self, tmp_path):
        p = self._file(tmp_path)
        p.write_bytes(p.read_bytes()[:-10])
        with pytest.raises(ValueError, match=r"g\.ply: corrupt PLY .*early end-of-file"):
            load_ply(p)

    def test_vertex_count_larger_than_data(self, tmp_path):
        p = self._file(tmp_path)
        p.write_bytes(p.read_bytes().replace(b"element vertex 4", b"element vertex 9"))
        with pytest.raises(ValueError, match=r"g\.ply: corrupt PLY"):
            load_ply(p)

    def test_missing_property_and_bad_sh(self, tmp_path):
        p = self._file(tmp_path)
        p.write_bytes(p.read_bytes().replace(b"property float opacity", b"property float opaque"))
        with pytest.raises(ValueError, match=r"missing vertex properties \['opacity'\]"):
            load_ply(p)
        p = self._file(tmp_path)
        p.write_bytes(p.read_bytes().replace(b"property float f_rest_8", b"property float extra"))
        with pytest.raises(ValueError, match="f_rest properties do not make a full SH degree"):
            load_ply(p)

    def test_empty_and_missing_file(self, tmp_path):
        (tmp_path / "e.ply").write_bytes(b"")
        with pytest.raises(ValueError, match="not a PLY file"):
            load_ply(tmp_path / "e.ply")
        with pytest.raises(FileNotFoundError, match="no PLY file"):
            load_ply(tmp_path / "none.ply")

    def test_atomic_write_leaves_no_temporary(self, tmp_path):
        self._file(tmp_path)
        assert [p.name for p in tmp_path.iterdir()] == ["g.ply"]

    def test_raw_round_trip_is_byte_identical(self, tmp_path):
        from vadgs.render import read_raw_ply, write_raw_ply

        p = self._file(tmp_path, k=9)
        write_raw_ply(tmp_path / "h.ply", read_raw_ply(p))
        assert (tmp_path / "h.ply").read_bytes() == p.read_bytes()
