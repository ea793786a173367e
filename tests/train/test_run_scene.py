"""A run knows its scene (absolute path, fingerprint, ``--scene``); one writer per run; ``--overwrite``.

Issue 33 (3, 4) and issue 32 (2, 5): ``eval`` run from another folder with a decoy scene at the
same relative path uses the run's own scene; a moved scene is a clear error naming ``--scene``,
which points the run at it; two trains into one ``--out`` fail by pid; a crashed run's lock is
taken over; ``vadgs demo`` re-runs.
"""

from __future__ import annotations

import json
import os
import shutil
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

from vadgs.cli import main as _main
from vadgs.runlock import LOCK_NAME, RunInUseError, RunLock
from vadgs.train.checkpoint import load_checkpoint
from vadgs.train.run import load_run, train_scene
from vadgs.train.scenes import open_scene, scene_fingerprint, scene_ref

from ..data.sample_copy import copy_sample_scene

TINY = ["--scale", "0.25", "--no-progress", "--init.max-points", "200", "--init.voxel-size", "1.0"]
TINY += ["--init.sh-degree", "0"]


def main(argv: list[str]) -> int:
    return _main(argv if argv[0] == "--threads" else ["--threads", "1", *argv])


def _error_line(capsys) -> str:
    err = capsys.readouterr().err
    assert "Traceback" not in err
    lines = [ln for ln in err.strip().splitlines() if "Warning" not in ln]
    assert len(lines) == 1, err
    return lines[0]


def _decoy(meta: dict) -> None:
    """Another scene: the test frames of the sample become training frames."""
    meta["split"] = {"train_frames": [16, 17, 18, 19, 20, 22], "test_frames": [21, 23]}


@pytest.fixture
def trained(tmp_path, monkeypatch):
    """A run trained from ``tmp_path/a`` on the scene ``scene`` given by a *relative* path."""
    home = tmp_path / "a"
    home.mkdir()
    copy_sample_scene(home)
    monkeypatch.chdir(home)
    run = tmp_path / "run"
    assert main(["train", "scene", "--out", str(run), "--iterations", "2", *TINY]) == 0
    return home, run


class TestRunKnowsItsScene:
    def test_recorded_absolutely_with_a_fingerprint(self, trained):
        home, run = trained
        ref = load_checkpoint(run).scene_ref
        assert ref["path"] == str((home / "scene").resolve()) and ref["run_dir"] == str(run.resolve())
        assert json.loads((run / "config.json").read_text())["scene"] == ref
        opened = load_run(run).scene
        assert ref["fingerprint"] == scene_fingerprint(ref, opened)
        # the fingerprint is of the content, not of the place: a copy has it, a changed scene not
        copy = {**ref, "path": str(copy_sample_scene(home / "copy"))}
        assert scene_fingerprint(copy, open_scene(copy)) == ref["fingerprint"]
        images = Path(copy["path"]) / "images/front"
        assert (images / "017.png").stat().st_size != (images / "016.png").stat().st_size
        shutil.copy(images / "017.png", images / "016.png")  # another image in its place
        assert scene_fingerprint(copy, open_scene(copy)) != ref["fingerprint"]
        shutil.copy(home / "scene/images/front/016.png", images / "016.png")
        meta = json.loads((Path(copy["path"]) / "scene.json").read_text())
        (Path(copy["path"]) / "scene.json").write_text(json.dumps({**meta, "description": "edited"}))
        assert scene_fingerprint(copy, open_scene(copy)) != ref["fingerprint"]  # its metadata

    def test_eval_from_another_folder_with_a_decoy_uses_the_runs_scene(
        self, trained, tmp_path, monkeypatch, capsys
    ):
        home, run = trained
        metrics = json.loads((run / "metrics.json").read_text())
        elsewhere = tmp_path / "b"
        elsewhere.mkdir()
        decoy = copy_sample_scene(elsewhere, _decoy)  # "scene" relative to the new current folder
        monkeypatch.chdir(elsewhere)
        assert main(["eval", str(run), "--no-progress"]) == 0
        ev = json.loads((run / "eval.json").read_text())
        assert ev["scene"]["path"] == str((home / "scene").resolve())  # the run's, not the decoy
        assert ev["scene"]["fingerprint"] == load_checkpoint(run).scene_ref["fingerprint"]
        assert ev["num_views"] == metrics["test"]["num_views"] == 6
        assert ev["psnr"] == pytest.approx(metrics["test"]["psnr"], abs=1e-6)
        capsys.readouterr()
        # pointed at the decoy explicitly: refused, naming both scenes and both fingerprints
        assert main(["eval", str(run), "--scene", "scene", "--no-progress"]) == 2
        line = _error_line(capsys)
        recorded = load_checkpoint(run).scene_ref["fingerprint"]
        assert str(decoy.resolve()) in line and str((home / "scene").resolve()) in line
        assert recorded in line and "is not the scene run" in line and "--scene FOLDER" in line
        assert json.loads((run / "eval.json").read_text()) == ev  # not overwritten

    def test_moved_scene_is_named_and_scene_points_at_it(self, trained, tmp_path, capsys):
        home, run = trained
        moved = tmp_path / "moved"
        shutil.move(home / "scene", moved)
        for cmd in (["eval", str(run)], ["render", str(run), "--views", "0"], ["export", str(run)]):
            assert main([*cmd, "--no-progress"] if cmd[0] != "export" else cmd) == 2
            line = _error_line(capsys)
            assert f"its benchmark scene is not at {(home / 'scene').resolve()}" in line, line
            assert "pass --scene FOLDER" in line
        assert main(["eval", str(run), "--scene", str(moved), "--no-progress"]) == 0
        assert json.loads((run / "eval.json").read_text())["scene"]["path"] == str(moved.resolve())
        assert main(["render", str(run), "--views", "0", "--no-progress", "--scene", str(moved)]) == 0
        assert len(list((run / "renders").glob("*.png"))) == 1
        assert main(["export", str(run), "--scene", str(moved)]) == 0
        assert list((run / "export").rglob("*.ply"))
        # a resumed run needs it too, and records where the scene is now
        assert main(["train", "--out", str(run), "--resume", "--iterations", "3", "--no-progress"]) == 2
        assert "give SCENE (the folder the scene moved to)" in _error_line(capsys)
        assert (
            main(["train", str(moved), "--out", str(run), "--resume", "--iterations", "3", *TINY[2:3]]) == 0
        )
        assert load_checkpoint(run).scene_ref["path"] == str(moved.resolve())
        assert main(["eval", str(run), "--no-progress"]) == 0  # no --scene needed any more
        # --scene of another kind is refused by the one function that decides kinds
        colmap = tmp_path / "notascene"
        colmap.mkdir()
        assert main(["eval", str(run), "--scene", str(colmap)]) == 2
        assert "neither a benchmark scene" in _error_line(capsys)


def test_moved_colmap_run_and_project(tmp_path, monkeypatch, capsys):
    """A distorted COLMAP run reads its undistorted copy from wherever the run folder moved."""
    pytest.importorskip("pycolmap")
    from ..data.colmap_sample import write_sample_colmap

    proj, run = tmp_path / "proj", tmp_path / "run"
    write_sample_colmap(proj, model="SIMPLE_RADIAL", k=0.02, n_points=200)
    assert main(["train", str(proj), "--out", str(run), "--iterations", "1", *TINY]) == 0
    psnr = json.loads((run / "metrics.json").read_text())["test"]["psnr"]
    shutil.move(run, tmp_path / "run2")
    shutil.move(proj, tmp_path / "proj2")
    monkeypatch.chdir(tmp_path / "proj2")
    assert main(["eval", str(tmp_path / "run2"), "--no-progress"]) == 0
    ev = json.loads((tmp_path / "run2" / "eval.json").read_text())
    assert ev["scene"]["path"] == str((tmp_path / "run2" / "undistorted" / "sparse").resolve())
    assert ev["psnr"] == pytest.approx(psnr, abs=1e-6)


class TestRunLock:
    def test_second_writer_is_refused_by_pid_and_released_on_any_exit(self, tmp_path):
        folder = tmp_path / "run"
        with RunLock(folder, "vadgs train") as lock:
            record = json.loads(lock.path.read_text())
            assert record["pid"] == os.getpid() and record["host"] == socket.gethostname()
            with pytest.raises(RunInUseError, match=rf"in use by vadgs train \(pid {os.getpid()} on "):
                RunLock(folder).acquire()
            with pytest.raises(RunInUseError):
                RunLock.check_free(folder)
        assert not folder.exists()  # made by the lock, left empty: removed
        folder.mkdir()
        with pytest.raises(KeyboardInterrupt), RunLock(folder):
            raise KeyboardInterrupt
        assert not (folder / LOCK_NAME).exists()
        RunLock.check_free(folder)
        with RunLock(folder):  # free again
            pass

    def test_stale_lock_of_a_dead_pid_is_taken_over(self, tmp_path, tiny_config):
        dead = subprocess.Popen([sys.executable, "-c", "pass"])
        dead.wait()
        run = tmp_path / "run"
        run.mkdir()
        stale = {"pid": dead.pid, "host": socket.gethostname(), "started": "then", "command": "vadgs train"}
        (run / LOCK_NAME).write_text(json.dumps(stale))
        RunLock.check_free(run)  # nobody holds it
        said: list[str] = []
        import dataclasses

        from vadgs.data import sample_scene_path

        config = dataclasses.replace(tiny_config, iterations=1)
        outcome = train_scene(
            scene_ref(sample_scene_path(), scale=0.25), config, run, progress=False, log=said.append
        )
        assert outcome.completed
        took = [s for s in said if "took over the lock" in s]
        assert len(took) == 1 and f"pid {dead.pid}" in took[0] and "not running" in took[0], said
        assert not (run / LOCK_NAME).exists()

    def test_two_trains_into_one_out(self, tmp_path, capsys):
        run = tmp_path / "run"
        env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[2])}
        args = ["train", "--sample", "--out", str(run), "--iterations", "100000", *TINY]
        first = subprocess.Popen(
            [sys.executable, "-m", "vadgs.cli", "--threads", "1", *args],
            env=env,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.PIPE,
            text=True,
        )
        try:
            deadline = time.monotonic() + 300
            while time.monotonic() < deadline and first.poll() is None:
                if (run / LOCK_NAME).is_file() and (run / "config.json").is_file():
                    break
                time.sleep(0.2)
            assert first.poll() is None, first.stderr.read()
            for extra in ([], ["--overwrite"]):
                assert main([*args, *extra]) == 2
                line = _error_line(capsys)
                assert line.startswith(
                    f"vadgs train: error: {run}: in use by vadgs train (pid {first.pid} "
                ), line
            assert main(["eval", str(run)]) == 2  # a writer into the run waits its turn too
            assert f"(pid {first.pid} " in _error_line(capsys)
            first.terminate()  # SIGTERM: the run checkpoints, exits 130 and releases the lock
            assert first.wait(timeout=300) == 130
        finally:
            if first.poll() is None:
                first.kill()
        assert not (run / LOCK_NAME).exists() and (run / "checkpoint.pt").is_file()


class TestOverwrite:
    def test_demo_reruns_and_names_overwrite_for_another_run(self, tmp_path, capsys):
        out = tmp_path / "demo"
        args = ["demo", "--out", str(out), "--iterations", "2", "--baseline", "--no-progress"]
        assert main(args) == 0
        assert main(args) == 0  # re-running the demo just works, and says what it replaced
        assert f"replacing the previous demo in {out} (step 2/2)" in capsys.readouterr().out
        assert json.loads((out / "metrics.json").read_text())["steps"] == 2
        run = tmp_path / "run"
        assert main(["train", "--sample", "--out", str(run), "--iterations", "1", *TINY]) == 0
        capsys.readouterr()
        assert main([*args[:2], str(run), *args[3:]]) == 2
        line = _error_line(capsys)
        assert "holds a run (step 1/1) that is not a demo's; pass --overwrite" in line
        assert "Trainer" not in line and "overwrite=True" not in line
        assert main([*args[:2], str(run), *args[3:], "--overwrite"]) == 0
        assert (run / "demo_panel.png").is_file()


def test_sigterm_after_importing_pycolmap_reaches_python():
    """pycolmap's glog takes SIGTERM over in C (native stack, no ``finally``); reclaim_signals undoes it."""
    pytest.importorskip("pycolmap")
    code = (
        "import os, signal, sys\n"
        "from vadgs.train.session import reclaim_signals\n"
        "signal.signal(signal.SIGTERM, lambda *a: sys.exit(7))\n"
        "import pycolmap\n"
        "if sys.argv[1] == 'reclaim':\n"
        "    reclaim_signals()\n"
        "os.kill(os.getpid(), signal.SIGTERM)\n"
        "signal.pause()\n"
    )
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[2])}
    run = [sys.executable, "-c", code]
    done = subprocess.run([*run, "reclaim"], env=env, capture_output=True, text=True, timeout=300)
    assert done.returncode == 7 and "SIGTERM" not in done.stderr, done.stderr
    glog = subprocess.run([*run, "no"], env=env, capture_output=True, text=True, timeout=300)
    assert glog.returncode == -15 and "SIGTERM" in glog.stderr  # what a run without it did
