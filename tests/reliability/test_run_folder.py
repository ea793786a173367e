"""Issue 39, item 1: a run folder knows what it wrote.

Each case runs as a user would (``vadgs.cli.main``) in a temporary folder, and checks, by a hash of
the whole tree, that nothing but what vadgs wrote changed: ``--overwrite`` removes exactly the
recorded files, a folder that is not a run is refused with or without ``--overwrite``, a refused
overwrite leaves the old run whole, ``export --inria`` does not write over another model.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
from pathlib import Path

import pytest

from tests.reliability.conftest import TINY
from vadgs.cli import main
from vadgs.runfolder import MANIFEST, check_output_folder, recorded_files
from vadgs.train.checkpoint import CHECKPOINT_NAME, load_checkpoint


def folder_tree(root: Path) -> dict[str, str]:
    """Every entry under ``root`` (links not followed): its content's hash, a link's target, or a folder."""
    out = {}
    for dirpath, dirnames, filenames in os.walk(root):
        for name in dirnames + filenames:
            p = Path(dirpath) / name
            rel = p.relative_to(root).as_posix()
            if p.is_symlink():
                out[rel] = "-> " + os.readlink(p)
            elif p.is_dir():
                out[rel] = "dir"
            else:
                out[rel] = hashlib.sha256(p.read_bytes()).hexdigest()
    return out


def error_line(capsys) -> str:
    err = capsys.readouterr().err
    assert "Traceback" not in err
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    return lines[0]


def _user_folder(path: Path) -> Path:
    """A user's folder that happens to use vadgs's names."""
    for rel, text in {
        "renders/holiday.jpg": "jpeg",
        "export/thesis.pdf": "pdf",
        "ply/scan.ply": "ply",
        "eval.json": "{}",
        "config.json": '{"mine": 1}',
        "log.jsonl": "my log\n",
    }.items():
        (path / rel).parent.mkdir(parents=True, exist_ok=True)
        (path / rel).write_text(text)
    return path


@pytest.mark.parametrize("overwrite", [[], ["--overwrite"]])
def test_user_folder_refused_and_untouched(tmp_path, capsys, overwrite):
    folder = _user_folder(tmp_path / "mine")
    before = folder_tree(tmp_path)
    assert main(["train", "--sample", "--out", str(folder), *TINY, *overwrite]) == 2
    line = error_line(capsys)
    assert f"destination path '{folder}' already exists and is not an empty directory" in line
    assert "holds config.json, eval.json, export, log.jsonl, ply, ... (6 entries)" in line
    assert folder_tree(tmp_path) == before  # config.json and log.jsonl kept too


def test_symlinked_out_to_user_folder_refused(tmp_path, capsys):
    folder = _user_folder(tmp_path / "mine")
    link = tmp_path / "link"
    link.symlink_to(folder)
    before = folder_tree(tmp_path)
    assert main(["train", "--sample", "--out", str(link), *TINY, "--overwrite"]) == 2
    assert "already exists and is not an empty directory" in error_line(capsys)
    assert folder_tree(tmp_path) == before


def test_python_api_refuses_a_user_folder(tmp_path, tiny_scene, tiny_config):
    from vadgs.train.run import train_scene
    from vadgs.train.scenes import scene_ref
    from vadgs.train.trainer import Trainer

    folder = _user_folder(tmp_path / "mine")
    before = folder_tree(tmp_path)
    with pytest.raises(ValueError, match="not an empty directory"):
        Trainer(tiny_scene, tiny_config, out_dir=folder, overwrite=True)
    with pytest.raises(ValueError, match="not an empty directory"):
        ref = scene_ref(tiny_scene.root, scale=0.25)
        train_scene(ref, tiny_config, folder, overwrite=True, progress=False)
    assert folder_tree(tmp_path) == before


def test_empty_folder_and_new_path_are_fine(tmp_path):
    (tmp_path / "empty").mkdir()
    assert main(["train", "--sample", "--out", str(tmp_path / "empty"), *TINY]) == 0
    assert main(["train", "--sample", "--out", str(tmp_path / "new" / "run"), *TINY]) == 0
    assert (tmp_path / "empty" / MANIFEST).is_file()
    names = {p.relative_to(tmp_path / "empty").as_posix() for p in recorded_files(tmp_path / "empty")}
    assert {CHECKPOINT_NAME, "config.json", "log.jsonl", "metrics.json", "ply/static.ply"} <= names


def _user_files_in_run(run: Path) -> dict[str, str]:
    (run / "renders").mkdir(exist_ok=True)
    (run / "renders" / "drive.mp4").write_bytes(b"my video")
    (run / "notes.txt").write_text("notes")
    (run / "ply" / "mine.ply").write_text("my ply")
    return {"renders/drive.mp4": "my video", "notes.txt": "notes", "ply/mine.ply": "my ply"}


def test_overwrite_keeps_user_files_and_says_what_it_removed(run, capsys):
    assert main(["render", str(run), "--no-progress", "--views", "0"]) == 0  # a panel: vadgs's
    panels = sorted((run / "renders").glob("view*.png"))
    assert len(panels) == 1
    mine = _user_files_in_run(run)
    capsys.readouterr()
    assert main(["train", "--sample", "--out", str(run), *TINY, "--overwrite"]) == 0
    out = capsys.readouterr().out
    assert f"overwrite: removed 10 files of the previous run from {run}" in out  # 9 of train, the panel
    for rel, text in mine.items():
        assert (run / rel).read_text() == text
    assert not panels[0].exists()
    load_checkpoint(run)  # the new run


@pytest.mark.parametrize("target", ["user", "dangling"])
def test_symlinked_ply_refused_before_anything_is_removed(run, tmp_path, capsys, target):
    user = tmp_path / "user_ply"
    user.mkdir()
    (user / "static.ply").write_text("the user's")
    shutil.rmtree(run / "ply")
    (run / "ply").symlink_to(user if target == "user" else tmp_path / "nowhere")
    before = folder_tree(tmp_path)
    assert main(["train", "--sample", "--out", str(run), *TINY, "--overwrite"]) == 2
    line = error_line(capsys)
    assert f"{run / 'ply'} is a symbolic link" in line and "nothing was removed" in line
    assert folder_tree(tmp_path) == before
    assert load_checkpoint(run).step == 2  # the old run is whole


def test_finished_run_without_checkpoint_is_not_told_to_resume(run, capsys):
    (run / CHECKPOINT_NAME).unlink()
    assert main(["train", "--sample", "--out", str(run), *TINY]) == 2
    line = error_line(capsys)
    assert "finished run whose checkpoint is gone" in line and "--overwrite" in line
    assert "--resume" not in line


def test_export_inria_refuses_scene_folder_and_another_model(run, tmp_path, capsys):
    scene = Path(json.loads((run / "config.json").read_text())["scene"]["path"])
    before_scene = folder_tree(scene)
    assert main(["export", str(run), "--inria", "--out", str(scene)]) == 2
    assert "scene folder" in error_line(capsys)
    assert folder_tree(scene) == before_scene

    other = tmp_path / "other_model"
    other.mkdir()
    (other / "cfg_args").write_text("Namespace(sh_degree=3)")
    (other / "cameras.json").write_text("[]")
    before = folder_tree(tmp_path)
    assert main(["export", str(run), "--inria", "--out", str(other)]) == 2
    assert "holds cfg_args, cameras.json that vadgs did not write" in error_line(capsys)
    assert folder_tree(tmp_path) == before
    assert main(["export", str(run), "--out", str(other)]) == 2  # not --inria: a folder vadgs did not write
    assert "not an empty directory" in error_line(capsys)
    (run / "cfg_args").write_text("Namespace(sh_degree=3)")  # another model's, in the run folder itself
    before = folder_tree(tmp_path)
    assert main(["export", str(run), "--inria", "--out", str(run)]) == 2
    assert "cfg_args that vadgs did not write" in error_line(capsys)
    assert folder_tree(tmp_path) == before

    fresh = tmp_path / "fresh"  # a new folder, then again into the folder vadgs wrote
    assert main(["export", str(run), "--inria", "--out", str(fresh)]) == 0
    assert main(["export", str(run), "--inria", "--out", str(fresh)]) == 0
    assert (fresh / MANIFEST).is_file()


def test_render_panels_into_a_user_folder_refused(run, tmp_path, capsys):
    folder = _user_folder(tmp_path / "mine")
    before = folder_tree(tmp_path)
    assert main(["render", str(run), "--no-progress", "--out", str(folder)]) == 2
    assert "not an empty directory" in error_line(capsys)
    assert folder_tree(tmp_path) == before


def test_batch_refuses_a_user_folder(tmp_path, capsys):
    from vadgs.data import sample_scene_path

    folder = _user_folder(tmp_path / "mine")
    before = folder_tree(tmp_path)
    assert main(["batch", str(sample_scene_path()), "--out", str(folder)]) == 2
    assert "not an empty directory" in error_line(capsys)
    assert folder_tree(tmp_path) == before


def test_sfm_refuses_a_folder_with_no_project(tmp_path, capsys):
    from vadgs.data import sample_scene_path

    photos = tmp_path / "photos"
    photos.mkdir()
    for p in sorted((sample_scene_path() / "images").rglob("*.png"))[:3]:
        shutil.copy(p, photos / p.name)
    folder = _user_folder(tmp_path / "mine")
    before = folder_tree(tmp_path)
    assert main(["sfm", str(photos), "--out", str(folder)]) == 2
    assert "not an empty directory" in error_line(capsys)
    assert folder_tree(tmp_path) == before


def test_check_output_folder_lists_a_few_entries(tmp_path):
    for i in range(8):
        (tmp_path / f"f{i}").write_text("x")
    with pytest.raises(ValueError, match=r"holds f0, f1, f2, f3, f4, \.\.\. \(8 entries\)"):
        check_output_folder(tmp_path)
