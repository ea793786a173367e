"""The CLI's error contract: one line naming the argument or file, exit code != 0, no traceback.

One test per CLI row of the reliability trial (issue 17), plus ``vadgs check``.
"""

from __future__ import annotations

import dataclasses
import json
import os
import shutil

import pytest

from vadgs import cli
from vadgs.cli import main
from vadgs.data import sample_scene_path

TINY = ["--scale", "0.25", "--no-progress", "--init.max-points", "300", "--init.voxel-size", "1.0"]
TINY += ["--init.sh-degree", "0"]
NO_COMMAND = "vadgs: error: expected a command (sfm, check, visibility, train, eval, render, export, view, "
NO_COMMAND += "demo, convert, batch)"


def _error_line(capsys) -> str:
    err = capsys.readouterr().err
    assert "Traceback" not in err
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    return lines[0]


class TestCheckCommand:
    def test_clean_scene(self, capsys):
        assert main(["check"]) == 0
        out = capsys.readouterr().out
        assert out.splitlines()[0].split() == ["status", "check", "file", "message"]
        assert "ok (10 checks" in out

    def test_full_with_errors(self, tmp_path, capsys):
        root = tmp_path / "scene"
        shutil.copytree(sample_scene_path(), root)
        (root / "images/front/019.png").write_bytes(b"")
        p = root / "images/front/020.png"
        p.write_bytes(p.read_bytes()[:400])
        assert main(["check", str(root)]) == 1
        out = capsys.readouterr().out
        assert "019.png" in out and "020.png" not in out and "1 error(s)" in out
        assert main(["check", str(root), "--full"]) == 1
        out = capsys.readouterr().out
        assert "020.png" in out and "2 error(s)" in out

    def test_missing_scene(self, tmp_path, capsys):
        assert main(["check", str(tmp_path)]) == 1
        assert "no scene.json" in capsys.readouterr().out


class TestArguments:
    @pytest.mark.parametrize(
        ("argv", "line"),
        [
            (
                ["--threads", "-1", "check"],
                "vadgs check: error: --threads: expected an integer in [0, 1024], got -1",
            ),
            (
                ["--threads", "two", "check"],
                "vadgs check: error: --threads: invalid literal for int() with base 10: 'two'",
            ),
            (["check", "--scale", "0"], "vadgs check: error: --scale: expected a finite number > 0, got 0.0"),
            (["check", "--bogus"], "vadgs check: error: Unrecognized options: --bogus"),
            (["eval"], "vadgs eval: error: missing RUN (see --help)"),
            (
                ["eval", "run", "--split", "train"],
                "vadgs eval: error: invalid choice 'train' for argument '--split'. "
                "Expected one of ('test', 'novel').",
            ),
            (
                ["view", "run", "--port", "0"],
                "vadgs view: error: --port: expected an integer in [1, 65535], got 0",
            ),
            (
                ["view", "run", "--timeout", "-3"],
                "vadgs view: error: --timeout: expected None or a finite number > 0, got -3.0",
            ),
            (
                ["render", "run", "--fps", "0"],
                "vadgs render: error: --fps: expected a finite number > 0, got 0.0",
            ),
            (
                ["export", "run", "--frame", "x"],
                "vadgs export: error: --frame: invalid literal for int() with base 10: 'x'",
            ),
            (
                ["convert", "waymo", "src", "--out", "o"],
                "vadgs convert: error: --scene: required for waymo (the scene or segment name in SRC)",
            ),
            (
                ["convert", "waymo", "src", "--scene", "s", "--out", "o", "--frames", "a:b"],
                "vadgs convert: error: --frames: expected START:STOP or one position, got 'a:b'",
            ),
            (
                ["batch", "--out", "o"],
                "vadgs batch: error: SCENE: expected at least one scene folder, got none",
            ),
            (
                ["batch", "a", "--out", "o", "--max-retries", "-1"],
                "vadgs batch: error: --max-retries: expected an integer >= 0, got -1",
            ),
            (
                ["demo", "--iterations", "-1"],
                "vadgs demo: error: --iterations: expected None or an integer >= 0, got -1",
            ),
            (
                ["visibility", "--view", "-1"],
                "vadgs visibility: error: --view: expected None or an integer >= 0, got -1",
            ),
            (
                ["frobnicate"],
                f"{NO_COMMAND}, got 'frobnicate'",
            ),
            (
                [],
                f"{NO_COMMAND}, got none",
            ),
            (["--threads", "2", "frobnicate"], f"{NO_COMMAND}, got 'frobnicate'"),  # not the flag's '2'
            (["--debug", "--threads", "2"], f"{NO_COMMAND}, got none"),
        ],
    )
    def test_rejected_by_the_parser(self, argv, line, tmp_path, monkeypatch, capsys):
        """Every command's flags are parsed by tyro and checked by its dataclass: one line, exit 2."""
        monkeypatch.chdir(tmp_path)  # nothing is written: the arguments fail before any work
        assert main(argv) == 2
        assert _error_line(capsys) == line
        assert list(tmp_path.iterdir()) == []

    @pytest.mark.parametrize("command", ["", *cli.COMMANDS])
    def test_help(self, command, capsys):
        """``vadgs --help`` lists the commands; ``vadgs COMMAND --help`` its flags, both exit 0."""
        assert main([command, "--help"] if command else ["--help"]) == 0
        out = capsys.readouterr().out
        assert out.startswith(f"usage: vadgs {command}".rstrip())
        assert "--threads" in out and "--debug" in out
        if not command:
            assert all(f"  {name} " in out for name in cli.COMMANDS)

    @pytest.mark.parametrize(
        ("flags", "line"),
        [
            (["--max-minutes", "-1"], "--max-minutes: expected a finite number >= 0 (0 = no limit), got -1"),
            (["--max-minutes", "inf"], "--max-minutes: expected a finite number >= 0 (0 = no limit), got i"),
            (["--iterations", "-5"], "--iterations: expected an integer >= 1, got -5"),
            (["--log-every", "0"], "--log-every: expected an integer >= 1, got 0"),
            (["--geometry.hard-every", "0"], "--geometry.hard-every: expected an integer >= 1, got 0"),
            (
                ["--geometry.hard-fused"],
                "--geometry.hard-fused: expected geometry.hard_stride 1, raster.backend 'torch' and no "
                "antialiasing, got geometry.hard_stride 2",
            ),
            (["--lr.means", "fast"], "--lr.means: could not convert string to float: 'fast'"),
            (["--iterations", "x"], "--iterations: invalid literal for int() with base 10: 'x'"),
            (["--scale", "0"], "--scale: expected None or a finite number > 0, got 0.0"),
            (
                ["--init.max-points", "many"],
                "--init.max-points: invalid literal for int() with base 10: 'many'",
            ),
            (
                ["--raster.backend", "vulkan"],
                "--raster.backend: expected one of ('torch', 'gsplat'), got 'vulkan'",
            ),
            (["--vad", "--vad.every-cycles", "0"], "--vad.every-cycles: expected an integer >= 1, got 0"),
            (["--bogus", "1"], "Unrecognized options: --bogus, 1"),
            (["--vad.max-instances", "3"], "Unrecognized options: --vad.max-instances, 3"),  # needs --vad
        ],
    )
    def test_train_flags_are_checked_in_one_line(self, flags, line, tmp_path, capsys):
        """tyro parses them; the dataclasses' own checks reject the values; exit 2, one line."""
        assert main(["train", "--sample", "--out", str(tmp_path / "x"), *flags]) == 2
        err = capsys.readouterr().err.strip()
        assert err.startswith(f"vadgs train: error: {line}") and "\n" not in err, err
        assert not (tmp_path / "x").exists()

    def test_moved_train_flags_are_unknown(self, tmp_path, capsys):
        """Nothing kept for compatibility (issue 50): the flat flags of the geometric loss (now
        ``--geometry.*``) are unknown flags, in one line, exit 2, as in ``vadgs batch --train-args``."""
        assert main(["train", "--sample", "--out", str(tmp_path / "x"), "--lambda-hard", "0.3"]) == 2
        assert _error_line(capsys) == "vadgs train: error: Unrecognized options: --lambda-hard, 0.3"
        assert main(["batch", "a", "--out", str(tmp_path / "b"), "--train-args=--hard-fused"]) == 2
        assert _error_line(capsys) == "vadgs batch: error: Unrecognized options: --hard-fused"
        assert not (tmp_path / "x").exists() and not (tmp_path / "b").exists()

    def test_out_is_a_file(self, tmp_path, capsys):
        f = tmp_path / "file.txt"
        f.write_text("x")
        assert main(["train", "--sample", "--out", str(f), *TINY]) == 2
        assert (
            _error_line(capsys) == f"vadgs train: error: --out {f}: expected a folder, got an existing file"
        )
        assert main(["visibility", "--out", str(f)]) == 2
        assert "--out" in _error_line(capsys)

    def test_out_cannot_be_created(self, tmp_path, capsys):
        f = tmp_path / "file.txt"
        f.write_text("x")
        assert main(["train", "--sample", "--out", str(f / "a" / "b"), *TINY]) == 2
        assert (
            _error_line(capsys)
            == f"vadgs train: error: --out {f / 'a' / 'b'}: cannot create the folder ({f} is a file)"
        )
        assert main(["demo", "--out", str(f / "sub"), "--iterations", "1"]) == 2
        assert f"--out {f / 'sub'}: cannot create the folder" in _error_line(capsys)

    @pytest.mark.skipif(os.name != "posix" or os.geteuid() == 0, reason="root can write anywhere")
    def test_out_read_only(self, tmp_path, capsys):
        ro = tmp_path / "ro"
        ro.mkdir()
        ro.chmod(0o500)
        try:
            assert main(["train", "--sample", "--out", str(ro), *TINY]) == 2
            assert "not writable" in _error_line(capsys)
        finally:
            ro.chmod(0o700)

    def test_config_with_a_string_where_a_number_goes(self, tmp_path, capsys):
        cfg = tmp_path / "c.json"
        cfg.write_text(json.dumps({"strategy": {"refine_every": "abc"}}))
        assert main(["train", "--sample", "--out", str(tmp_path / "r"), "--config", str(cfg), *TINY]) == 2
        line = _error_line(capsys)
        assert f"--config {cfg}.strategy.refine_every: expected int, got str 'abc'" in line

    def test_config_missing_or_invalid(self, tmp_path, capsys):
        assert (
            main(["train", "--sample", "--out", str(tmp_path / "r"), "--config", str(tmp_path / "no.json")])
            == 2
        )
        assert "--config" in _error_line(capsys)
        (tmp_path / "bad.json").write_text("{")
        assert (
            main(["train", "--sample", "--out", str(tmp_path / "r"), "--config", str(tmp_path / "bad.json")])
            == 2
        )
        assert "not valid JSON" in _error_line(capsys)


class TestErrorContract:
    def _raise(self, monkeypatch, exc):
        @dataclasses.dataclass(frozen=True)
        class Boom(cli.CheckCommand):
            """A command that fails."""

            def main(self) -> int:
                raise exc

        monkeypatch.setitem(cli.COMMANDS, "check", Boom)

    def test_unexpected_exception_is_one_line(self, monkeypatch, capsys):
        self._raise(monkeypatch, RuntimeError("kernel exploded\nsecond line"))
        assert main(["check"]) == 2
        line = _error_line(capsys)
        assert (
            line
            == "vadgs check: error: RuntimeError: kernel exploded second line (--debug shows the traceback)"
        )

    def test_debug_shows_the_traceback(self, monkeypatch, capsys):
        self._raise(monkeypatch, RuntimeError("kernel exploded"))
        assert main(["--debug", "check"]) == 2
        assert "Traceback" in capsys.readouterr().err

    def test_os_error_names_the_file(self, monkeypatch, capsys):
        self._raise(monkeypatch, PermissionError(13, "Permission denied", "/some/file"))
        assert main(["check"]) == 2
        assert _error_line(capsys) == "vadgs check: error: /some/file: Permission denied"

    def test_broken_pipe_is_quiet(self, monkeypatch, capsys):
        """``vadgs ... | head``: the reader went away; no error line, exit 141 as a shell's SIGPIPE."""
        self._raise(monkeypatch, BrokenPipeError(32, "Broken pipe"))
        assert main(["check"]) == 141
        assert capsys.readouterr().err == ""

    def test_floating_point_error_and_interrupt(self, monkeypatch, capsys):
        self._raise(monkeypatch, FloatingPointError("loss is NaN at step 3"))
        assert main(["check"]) == 3
        self._raise(monkeypatch, KeyboardInterrupt())
        assert main(["check"]) == 130


class TestRunPaths:
    def test_eval_and_render_of_the_checkpoint_file(self, tmp_path, capsys):
        out = tmp_path / "run"
        assert main(["train", "--sample", "--out", str(out), "--iterations", "1", *TINY]) == 0
        (out / "eval.json").unlink(missing_ok=True)
        assert main(["eval", str(out / "checkpoint.pt"), "--no-progress"]) == 0
        assert (out / "eval.json").is_file()
        assert main(["render", str(out / "checkpoint.pt"), "--views", "2", "--no-progress"]) == 0
        assert len(list((out / "renders").glob("*.png"))) == 1
