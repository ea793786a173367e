"""vadgs.data._json: one-line errors that name the file and the key."""

from __future__ import annotations

import pytest

from vadgs.data._json import read_json, require_key


class TestReadJson:
    def test_smoke(self, tmp_path):
        (tmp_path / "a.json").write_text('{"x": 1}')
        (tmp_path / "b.json").write_text("[1, 2]")
        assert read_json(tmp_path / "a.json", "A") == {"x": 1}
        assert read_json(tmp_path / "b.json", "B", top=list) == [1, 2]

    def test_exception(self, tmp_path):
        with pytest.raises(FileNotFoundError, match=r"^A: missing file .*a\.json$"):
            read_json(tmp_path / "a.json", "A")
        (tmp_path / "a.json").write_text('{"x": ')
        with pytest.raises(ValueError, match=r"^A: .*a\.json is not valid JSON \(") as e:
            read_json(tmp_path / "a.json", "A")
        assert "\n" not in str(e.value)
        (tmp_path / "a.json").write_text("[1]")
        with pytest.raises(ValueError, match=r"a\.json: expected a JSON object at the top level$"):
            read_json(tmp_path / "a.json", "A")
        (tmp_path / "a.json").write_text("{}")
        with pytest.raises(ValueError, match=r"a\.json: expected a JSON list at the top level$"):
            read_json(tmp_path / "a.json", "A", top=list)


class TestRequireKey:
    def test_smoke(self):
        assert require_key({"k": [1]}, "k", "where") == [1]

    @pytest.mark.parametrize("d", [{}, [], None, "k"])
    def test_exception(self, d):
        with pytest.raises(ValueError, match=r"^scene\.json: frames\[0\]: missing key 'index'$"):
            require_key(d, "index", "scene.json: frames[0]")
