"""Nothing kept for compatibility (issue 50): a checkpoint or a run folder of another format version
is refused in one line naming the file, the version found, the version read and that the run must
be trained again; a folder without a manifest is not vadgs's."""

from __future__ import annotations

import json

import pytest
import torch

from vadgs.cli import main
from vadgs.runfolder import FOLDER_VERSION, MANIFEST, ManifestError, check_output_folder, record_files
from vadgs.train.checkpoint import (
    CHECKPOINT_NAME,
    CHECKPOINT_VERSION,
    check_new_run,
    checkpoint_checksum,
    describe_run,
    load_checkpoint,
)

TINY = ["--scale", "0.25", "--no-progress", "--init.max-points", "300", "--init.sh-degree", "0"]


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    """A finished 2-step run of the bundled sample, in the current formats."""
    out = tmp_path_factory.mktemp("format") / "run"
    assert main(["train", "--sample", "--out", str(out), "--iterations", "2", *TINY]) == 0
    return out


def _error_line(capsys) -> str:
    err = capsys.readouterr().err.strip()
    assert "\n" not in err, err
    return err


def test_the_versions():
    assert (CHECKPOINT_VERSION, FOLDER_VERSION) == (2, 2)  # bumped once by issue 50, from 1


def test_a_run_is_written_in_the_current_versions(run):
    assert torch.load(run / CHECKPOINT_NAME, weights_only=True)["version"] == CHECKPOINT_VERSION
    assert json.loads((run / MANIFEST).read_text())["version"] == FOLDER_VERSION
    assert load_checkpoint(run).step == 2


def test_an_older_checkpoint_is_refused(run, tmp_path, capsys):
    old = tmp_path / "old"
    old.mkdir()
    ckpt = torch.load(run / CHECKPOINT_NAME, weights_only=True)
    ckpt["version"] = 1
    ckpt["checksum"] = checkpoint_checksum(ckpt)  # a sound file, of version 1
    torch.save(ckpt, old / CHECKPOINT_NAME)
    line = f"{old / CHECKPOINT_NAME}: format version 1, this vadgs reads version 2: train the run again"
    with pytest.raises(ValueError) as e:
        load_checkpoint(old)
    assert str(e.value) == line
    assert describe_run(old) == f"an unreadable checkpoint: {line}"
    record_files(old, [old / CHECKPOINT_NAME])  # a folder of this version: only the checkpoint is old
    assert main(["train", "--out", str(old), "--resume", "--no-progress"]) == 2
    assert _error_line(capsys) == f"vadgs train: error: {line}"
    assert main(["eval", str(old), "--no-progress"]) == 2
    assert _error_line(capsys).endswith(line)


def test_an_older_run_folder_is_refused(run, tmp_path, capsys):
    old = tmp_path / "old"
    (old / MANIFEST).parent.mkdir(parents=True)
    manifest = json.loads((run / MANIFEST).read_text())
    (old / MANIFEST).write_text(json.dumps({**manifest, "version": 1}))
    (old / "metrics.json").write_text("{}")
    line = f"{old / MANIFEST}: format version 1, this vadgs reads version 2: train the run again"
    line += " (in a new folder)"
    for call in (lambda: check_output_folder(old), lambda: record_files(old, [old / "metrics.json"])):
        with pytest.raises(ManifestError) as e:
            call()
        assert str(e.value) == line
    assert main(["train", "--sample", "--out", str(old), "--overwrite", *TINY]) == 2
    assert _error_line(capsys) == f"vadgs train: error: {line}"
    assert sorted(p.name for p in old.iterdir()) == [".vadgs", "metrics.json"]  # nothing removed


def test_a_run_without_a_manifest_is_not_vadgs(tmp_path):
    """A run from before the manifest (its checkpoint and config.json, no ``.vadgs/``) is a folder
    vadgs did not write: refused with or without overwrite, nothing removed."""
    old = tmp_path / "old"
    old.mkdir()
    (old / "config.json").write_text(json.dumps({"config": {"iterations": 2}, "scene": {}}))
    for overwrite in (False, True):
        with pytest.raises(
            ValueError, match=r"already exists and is not an empty directory \(holds config\.json\)"
        ):
            check_new_run(old, overwrite)
    assert [p.name for p in old.iterdir()] == ["config.json"]
