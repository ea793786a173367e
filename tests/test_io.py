"""vadgs.io: all or nothing, temporary files cleaned, the suffix kept for format-by-suffix writers."""

from __future__ import annotations

import json

import pytest

from vadgs.io import TMP_GLOB, atomic_write, remove_stale_tmp, write_json


def test_text_bytes_and_function(tmp_path):
    assert atomic_write(tmp_path / "a" / "t.txt", "héllo").read_text() == "héllo"
    assert atomic_write(tmp_path / "b.bin", b"\x00\x01").read_bytes() == b"\x00\x01"
    seen = []
    atomic_write(tmp_path / "c.png", lambda p: (seen.append(p), p.write_text("x")))
    assert seen[0].suffix == ".png" and seen[0].parent == tmp_path and not seen[0].exists()
    assert (tmp_path / "c.png").read_text() == "x"
    assert list(tmp_path.glob(TMP_GLOB)) == []


def test_failure_keeps_the_previous_file_and_removes_the_temporary(tmp_path):
    target = write_json(tmp_path / "metrics.json", {"psnr": 1.0})

    def half_written(p):
        p.write_text('{"psnr": ')
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        atomic_write(target, half_written)
    assert json.loads(target.read_text()) == {"psnr": 1.0}
    assert list(tmp_path.glob(TMP_GLOB)) == []


def test_bad_data_names_the_argument(tmp_path):
    with pytest.raises(TypeError, match="data must be str, bytes or a function of a path, got int"):
        atomic_write(tmp_path / "x", 3)


def test_remove_stale_tmp(tmp_path):
    (tmp_path / "ply").mkdir()
    left = [tmp_path / ".metrics.0a1b2c3d.tmp.json", tmp_path / "ply" / ".world.0a1b2c3d.tmp.ply"]
    for p in left:
        p.write_text("partial")
    (tmp_path / "keep.json").write_text("{}")
    assert sorted(remove_stale_tmp(tmp_path, "ply")) == sorted(left)
    assert [p.name for p in tmp_path.rglob("*") if p.is_file()] == ["keep.json"]
