"""Issue 49, items 1 and 2: vadgs removes and replaces only what it wrote.

A run's files are exactly its checked manifest's (an entry that leaves the run, by ``..``, an
absolute path or a symlinked folder, stops ``--overwrite`` before anything is removed), and a
folder is a vadgs run by what vadgs wrote into it (its manifest, a ``config.json`` that parses as
a vadgs config, a checkpoint that loads as a vadgs checkpoint), never by file names. Each case
runs the CLI as a user would and compares a hash of the whole tree before and after.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

from tests.reliability.conftest import TINY
from tests.reliability.test_run_folder import error_line, folder_tree
from vadgs.cli import main
from vadgs.runfolder import MANIFEST
from vadgs.train.checkpoint import CHECKPOINT_NAME, load_checkpoint


def _add_entry(run: Path, entry: str) -> None:
    path = run / MANIFEST
    data = json.loads(path.read_text())
    data["files"][entry] = {"size": 6}
    path.write_text(json.dumps(data))


@pytest.mark.parametrize("entry", ["../victim.txt", "ply/../../outside/v.txt"])
def test_manifest_entry_outside_the_run_stops_overwrite(run, tmp_path, capsys, entry):
    victim = (run / entry).resolve()
    victim.parent.mkdir(parents=True, exist_ok=True)
    victim.write_text("victim")
    _add_entry(run, entry)
    before = folder_tree(tmp_path)
    assert main(["train", "--sample", "--out", str(run), *TINY, "--overwrite"]) == 2
    line = error_line(capsys)
    assert f"{run / MANIFEST}: entry {entry!r}" in line and "nothing was removed" in line
    assert folder_tree(tmp_path) == before
    assert victim.read_text() == "victim"
    assert load_checkpoint(run).step == 2  # the old run is whole


def test_absolute_manifest_entry_stops_overwrite(run, tmp_path, capsys):
    victim = tmp_path / "victim.txt"
    victim.write_text("victim")
    _add_entry(run, str(victim))
    before = folder_tree(tmp_path)
    assert main(["train", "--sample", "--out", str(run), *TINY, "--overwrite"]) == 2
    line = error_line(capsys)
    assert f"entry {str(victim)!r} is an absolute path" in line and "nothing was removed" in line
    assert folder_tree(tmp_path) == before


def test_manifest_entry_through_a_symlinked_folder_stops_overwrite(run, tmp_path, capsys):
    user = tmp_path / "user"
    user.mkdir()
    (user / "v.txt").write_text("victim")
    (run / "notes").symlink_to(user)  # a link the user made inside the run
    _add_entry(run, "notes/v.txt")
    before = folder_tree(tmp_path)
    assert main(["train", "--sample", "--out", str(run), *TINY, "--overwrite"]) == 2
    line = error_line(capsys)
    assert f"entry 'notes/v.txt' passes through {run / 'notes'}, a symbolic link" in line
    assert str(run / MANIFEST) in line and "nothing was removed" in line
    assert folder_tree(tmp_path) == before


@pytest.mark.parametrize("damage", ["cut", "not_json", "other_format"])
@pytest.mark.parametrize("overwrite", [[], ["--overwrite"]])
def test_unreadable_manifest_stops_and_says_how_to_go_on(run, tmp_path, capsys, damage, overwrite):
    path = run / MANIFEST
    text = path.read_text()
    path.write_text(
        {"cut": text[: len(text) // 2], "not_json": "\0\0", "other_format": '{"files": {}}'}[damage]
    )
    before = folder_tree(tmp_path)
    assert main(["train", "--sample", "--out", str(run), *TINY, *overwrite]) == 2
    line = error_line(capsys)
    assert (
        f"{path}: unreadable" in line and "cannot tell which files" in line and "nothing was changed" in line
    )
    assert "give another folder" in line and "--overwrite" not in line and "--resume" not in line
    assert folder_tree(tmp_path) == before


def test_overwrite_line_lists_what_it_removes_first(run, capsys):
    recorded = json.loads((run / MANIFEST).read_text())["files"]
    assert main(["train", "--sample", "--out", str(run), *TINY, "--overwrite"]) == 0
    out = capsys.readouterr().out.splitlines()
    shown = next(i for i, s in enumerate(out) if "is removed as training starts:" in s)
    removed = next(i for i, s in enumerate(out) if s.startswith("overwrite: removed"))
    assert shown < removed  # shown before, as git clean -n
    first = ", ".join(sorted(recorded)[:6])
    assert out[shown].endswith(f"training starts: {first}, ... ({len(recorded)} files)"), out[shown]
    assert out[removed].startswith(f"overwrite: removed {len(recorded)} files of the previous run")


# -- item 2: a folder is a vadgs run by what vadgs wrote


def _foreign(kind: str, folder: Path) -> None:
    import torch

    folder.mkdir()
    if kind == "metrics":
        (folder / "metrics.json").write_text('{"acc": 0.93}')
    elif kind == "checkpoint":
        torch.save({"epoch": 3, "state_dict": {"w": torch.ones(2)}}, folder / CHECKPOINT_NAME)
    elif kind == "config":
        (folder / "config.json").write_text('{"config": {"lr": 0.1}, "scene": {}}')
    elif kind == "log":
        (folder / "log.jsonl").write_text('{"step": 1}\n')
    (folder / "results.csv").write_text("a,b\n")


@pytest.mark.parametrize("kind", ["metrics", "checkpoint", "config", "log"])
@pytest.mark.parametrize("flags", [[], ["--overwrite"], ["--resume"]])
def test_another_tools_files_are_not_a_run(tmp_path, capsys, kind, flags):
    folder = tmp_path / "theirs"
    _foreign(kind, folder)
    before = folder_tree(tmp_path)
    assert main(["train", *([] if flags == ["--resume"] else ["--sample"]), "--out", str(folder), *TINY,
                 *flags]) == 2  # fmt: skip
    line = error_line(capsys)
    if flags != ["--resume"]:
        names = {"metrics": "metrics.json", "checkpoint": CHECKPOINT_NAME, "config": "config.json"}
        assert f"holds {names.get(kind, 'log.jsonl')}, results.csv) nor a vadgs run folder" in line
    assert "--overwrite" not in line and "use --resume" not in line
    assert folder_tree(tmp_path) == before


def test_resume_refuses_another_projects_checkpoint(tmp_path, capsys):
    folder = tmp_path / "theirs"
    _foreign("checkpoint", folder)
    before = folder_tree(tmp_path)
    assert main(["train", "--out", str(folder), "--resume", "--no-progress"]) == 2
    assert "not a vadgs training checkpoint" in error_line(capsys)
    assert folder_tree(tmp_path) == before


def test_a_run_without_its_manifest_is_not_vadgs(run, tmp_path, capsys):
    """Nothing kept for compatibility (issue 50): vadgs knows its folders by their manifest only."""
    shutil.rmtree(run / ".vadgs")
    before = folder_tree(tmp_path)
    for flags in ([], ["--overwrite"]):
        assert main(["train", "--sample", "--out", str(run), *TINY, *flags]) == 2
        assert "nor a vadgs run folder" in error_line(capsys)
    assert folder_tree(tmp_path) == before


def test_another_projects_checkpoint_in_a_run_folder_is_not_written_over(run, tmp_path, capsys):
    import torch

    (run / CHECKPOINT_NAME).unlink()  # the run's own, gone from the folder and its manifest
    data = json.loads((run / MANIFEST).read_text())
    del data["files"][CHECKPOINT_NAME]
    (run / MANIFEST).write_text(json.dumps(data))
    torch.save({"epoch": 3}, run / CHECKPOINT_NAME)  # another project's, put there
    before = folder_tree(tmp_path)
    assert main(["train", "--sample", "--out", str(run), *TINY, "--overwrite"]) == 2
    assert f"holds {CHECKPOINT_NAME} that vadgs did not write" in error_line(capsys)
    assert folder_tree(tmp_path) == before


def test_eval_of_a_users_metrics_folder_does_not_call_it_a_run(tmp_path, capsys):
    folder = tmp_path / "theirs"
    _foreign("metrics", folder)
    assert main(["eval", str(folder)]) == 2
    line = error_line(capsys)
    assert "finished run" not in line


def test_batch_recognises_its_summary_by_content(tmp_path, capsys):
    from vadgs.batch import BatchSummary, check_batch_folder, write_summary
    from vadgs.data import sample_scene_path

    theirs = tmp_path / "theirs"
    theirs.mkdir()
    (theirs / "summary.json").write_text('{"acc": 0.93}')  # another tool's summary
    before = folder_tree(tmp_path)
    assert main(["batch", str(sample_scene_path()), "--out", str(theirs)]) == 2
    line = error_line(capsys)
    assert "holds summary.json) nor a vadgs batch folder" in line and "--overwrite" not in line
    assert folder_tree(tmp_path) == before

    ours = tmp_path / "ours"
    write_summary(BatchSummary(str(ours), (), 0.0))
    assert check_batch_folder(ours) == ours  # its manifest
    shutil.rmtree(ours / ".vadgs")  # a summary alone is not a batch's (issue 50: no older batches)
    with pytest.raises(ValueError, match=r"holds summary\.json, summary\.md\) nor a vadgs batch folder"):
        check_batch_folder(ours)


# -- vadgs sfm: a project is vadgs's when its sfm.json says so


def _sfm(photos: Path, out: Path, *flags: str) -> int:
    return main(["--threads", "1", "sfm", str(photos), "--out", str(out), "--no-progress", *flags])


@pytest.fixture(scope="module")
def photos(tmp_path_factory) -> Path:
    """Four photos of the test room, as tests/data/test_sfm.py's small project (three register)."""
    from tests.data.photo_sample import write_photo_set

    root = tmp_path_factory.mktemp("photos")
    keep = write_photo_set(root / "all")["names"][:4]
    (root / "photos").mkdir()
    for name in keep:
        shutil.copy(root / "all" / name, root / "photos" / name)
    return root / "photos"


@pytest.mark.parametrize("sfm_json", [None, '{"colmap": "3.9", "images": 4}'])
@pytest.mark.parametrize("overwrite", [[], ["--overwrite"]])
def test_sfm_never_writes_into_a_colmap_project_made_elsewhere(photos, tmp_path, capsys, sfm_json, overwrite):
    pytest.importorskip("pycolmap")
    project = tmp_path / "theirs"
    (project / "sparse" / "0").mkdir(parents=True)
    (project / "sparse" / "0" / "cameras.bin").write_bytes(b"\0" * 8)
    (project / "images").mkdir()
    (project / "images" / "IMG_0001.jpg").write_bytes(b"the only copy")
    (project / "database.db").write_bytes(b"SQLite format 3\0")
    if sfm_json is not None:
        (project / "sfm.json").write_text(sfm_json)
    before = folder_tree(tmp_path)
    assert _sfm(photos, project, *overwrite) == 2
    line = error_line(capsys)
    assert f"--out {project}: holds a COLMAP project that vadgs sfm did not write" in line
    assert ("its sfm.json is not vadgs sfm's" if sfm_json else "no sfm.json of vadgs sfm") in line
    assert "--overwrite" not in line
    assert folder_tree(tmp_path) == before


def test_sfm_overwrite_replaces_only_what_it_wrote_and_cleans_a_killed_runs_work(photos, tmp_path, capsys):
    import os

    pytest.importorskip("pycolmap")
    project = tmp_path / "proj"
    assert _sfm(photos, project) == 0
    summary = json.loads((project / "sfm.json").read_text())
    assert summary["format"] == "vadgs-sfm-project"
    assert summary["images_written"] == sorted(p.name for p in photos.iterdir())
    # the user's files in the project: a photo added to images/, notes, a second model
    (project / "images" / "extra.jpg").write_bytes(b"mine")
    (project / "notes.txt").write_text("notes")
    (project / "sparse" / "1").mkdir()
    (project / "sparse" / "1" / "cameras.txt").write_text("# mine")
    # work folders: a killed run's (marker, dead pid), one of a live process, one without a marker
    dead = project / ".vadgs-sfm-dead"
    dead.mkdir()
    import socket
    import subprocess
    import sys

    gone = [sys.executable, "-c", "import os; print(os.getpid())"]  # a pid no longer running
    proc = subprocess.run(gone, capture_output=True, text=True)
    marker = {"pid": int(proc.stdout), "host": socket.gethostname(), "started": 0}
    (dead / "vadgs-sfm-work.json").write_text(json.dumps(marker))
    (dead / "database.db").write_bytes(b"partial")
    live = project / ".vadgs-sfm-live"
    live.mkdir()
    (live / "vadgs-sfm-work.json").write_text(json.dumps({**marker, "pid": os.getppid()}))
    unmarked = project / ".vadgs-sfm-unmarked"
    unmarked.mkdir()
    capsys.readouterr()
    assert _sfm(photos, project, "--overwrite") == 0
    out = capsys.readouterr().out
    assert f"removed {dead}: the work folder of a killed vadgs sfm (pid {marker['pid']}, not running)" in out
    assert not dead.exists() and live.is_dir() and unmarked.is_dir()
    assert (project / "images" / "extra.jpg").read_bytes() == b"mine"
    assert (project / "notes.txt").read_text() == "notes"
    assert (project / "sparse" / "1" / "cameras.txt").read_text() == "# mine"
    names = sorted(["extra.jpg", *summary["images_written"]])
    assert sorted(p.name for p in (project / "images").iterdir()) == names
    for name in summary["images_written"]:
        assert (project / "images" / name).read_bytes() == (photos / name).read_bytes()


def test_sfm_project_without_its_format_is_not_vadgs(photos, tmp_path, capsys):
    """Nothing kept for compatibility (issue 50): an ``sfm.json`` without vadgs's format (what
    vadgs sfm wrote before it had one) is another tool's; nothing is removed."""
    pytest.importorskip("pycolmap")
    project = tmp_path / "proj"
    assert _sfm(photos, project) == 0
    summary = json.loads((project / "sfm.json").read_text())
    for key in ("format", "images_written"):
        del summary[key]
    (project / "sfm.json").write_text(json.dumps(summary))
    before = folder_tree(tmp_path)
    assert _sfm(photos, project, "--overwrite") == 2
    assert "vadgs sfm never writes into it, its images/ least of all: nothing was changed" in error_line(
        capsys
    )
    assert folder_tree(tmp_path) == before


# -- make_segment: only what it wrote

SEG = {"frames": 3, "cameras": 1, "width": 32, "height": 24, "lidar_points": 200, "progress": False}


def _segment_script(argv: list[str]) -> int:
    import importlib.util

    path = Path(__file__).resolve().parents[2] / "benchmarks" / "make_segment.py"
    spec = importlib.util.spec_from_file_location("_vadgs_make_segment", path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module.main(argv)


@pytest.mark.parametrize("overwrite", [False, True])
def test_make_segment_refuses_a_folder_it_did_not_write(tmp_path, capsys, overwrite):
    from vadgs.data.synthetic import make_segment

    folder = tmp_path / "mine"
    (folder / "images").mkdir(parents=True)
    (folder / "images" / "holiday.jpg").write_text("jpeg")
    (folder / "scene.json").write_text('{"name": "my scene"}')  # another tool's scene
    before = folder_tree(tmp_path)
    with pytest.raises(ValueError, match="not empty") as e:
        make_segment(folder, overwrite=overwrite, **SEG)
    assert "nor a segment that make_segment wrote" in str(e.value) and "overwrite" not in str(e.value)
    with pytest.raises(SystemExit):
        _segment_script([str(folder), "--frames", "2", *(["--overwrite"] if overwrite else [])])
    line = capsys.readouterr().err.strip().splitlines()[-1]  # argparse's usage, then the error
    assert (
        "holds images, scene.json) nor a segment that make_segment wrote" in line
        and "--overwrite" not in line
    )
    assert folder_tree(tmp_path) == before


def test_make_segment_overwrite_removes_only_what_it_wrote(tmp_path):
    from vadgs.data import load_scene
    from vadgs.data.synthetic import make_segment

    seg = make_segment(tmp_path / "seg", **SEG)
    (seg / "notes.txt").write_text("notes")
    (seg / "images" / "front" / "mine.png").write_text("mine")
    with pytest.raises(
        ValueError, match=r"not empty: a segment make_segment wrote \(overwrite=True replaces it\)"
    ):
        make_segment(seg, **SEG)
    make_segment(seg, overwrite=True, **{**SEG, "frames": 2})
    assert (seg / "notes.txt").read_text() == "notes"
    assert (seg / "images" / "front" / "mine.png").read_text() == "mine"
    assert sorted(p.name for p in (seg / "images" / "front").iterdir()) == ["000.jpg", "001.jpg", "mine.png"]
    assert sorted(p.name for p in (seg / "lidar").iterdir()) == ["000.npz", "001.npz"]  # frame 002's gone
    assert len(load_scene(seg).frames) == 2


def test_make_segment_killed_is_still_its_own_and_a_users_file_in_the_way_is_refused(tmp_path):
    from vadgs.data.synthetic import make_segment

    seg = make_segment(tmp_path / "seg", **SEG)
    (seg / "scene.json").unlink()  # killed before its last write: the manifest knows its files
    make_segment(seg, overwrite=True, **SEG)
    assert (seg / "scene.json").is_file()
    seg2 = make_segment(tmp_path / "seg2", **SEG)
    data = json.loads((seg2 / MANIFEST).read_text())
    del data["files"]["lidar/000.npz"]  # a file of that name that it did not record
    (seg2 / MANIFEST).write_text(json.dumps(data))
    before = folder_tree(tmp_path)
    with pytest.raises(ValueError, match=r"lidar/000\.npz is not a file make_segment wrote"):
        make_segment(seg2, overwrite=True, **SEG)
    assert folder_tree(tmp_path) == before


@pytest.mark.parametrize("command", ["export", "render"])
@pytest.mark.parametrize("kind", ["metrics", "checkpoint"])
def test_export_and_render_out_into_another_tools_folder_refused(run, tmp_path, capsys, command, kind):
    folder = tmp_path / "theirs"
    _foreign(kind, folder)  # a metrics.json / checkpoint.pt made vadgs take it for its own before
    before = folder_tree(tmp_path)
    extra = ["--no-progress", "--views", "0"] if command == "render" else []
    assert main([command, str(run), "--out", str(folder), *extra]) == 2
    line = error_line(capsys)
    assert "already exists and is not an empty directory" in line and "nor a vadgs output folder" in line
    assert "--overwrite" not in line
    assert folder_tree(tmp_path) == before


def test_eval_into_a_run_whose_manifest_is_unreadable_writes_nothing(run, tmp_path, capsys):
    (run / MANIFEST).write_text('{"format": "vadgs-folder-manifest", "files": {')  # cut short
    before = folder_tree(tmp_path)
    assert main(["eval", str(run), "--no-progress"]) == 2
    line = error_line(capsys)
    assert f"{run / MANIFEST}: unreadable" in line and "delete it yourself" in line
    assert folder_tree(tmp_path) == before  # no eval.json written beside a manifest that cannot record it


def test_a_segment_folder_is_no_run_folder_and_a_run_folder_no_segment(run, tmp_path, capsys):
    from vadgs.data.synthetic import make_segment

    seg = make_segment(tmp_path / "seg", **SEG)
    before = folder_tree(tmp_path)
    assert main(["train", "--sample", "--out", str(seg), *TINY, "--overwrite"]) == 2
    line = error_line(capsys)
    assert (
        f"--out {seg}: holds a segment that vadgs wrote (its manifest says so), not a vadgs run folder"
        in line
    )
    with pytest.raises(ValueError, match="holds a vadgs run or output folder, not a segment"):
        make_segment(run, overwrite=True, **SEG)
    assert folder_tree(tmp_path) == before
