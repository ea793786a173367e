"""Issue 39, a newcomer's findings: what a command says of photos, projects and scenes given in the
wrong place; eval's image names and the fingerprint it checked; the event summary's failures;
``--version``; the pixel size at ``--scale``."""

from __future__ import annotations

import hashlib
import json
import shutil
from pathlib import Path

import pytest
from PIL import Image

import vadgs
from vadgs.cli import main
from vadgs.cli._common import metrics_summary
from vadgs.data import load_scene, sample_scene_path
from vadgs.train.checkpoint import load_checkpoint
from vadgs.train.scenes import open_scene, scene_fingerprint
from vadgs.train.vad.config import VisibilityDensifyConfig
from vadgs.train.vad.event_log import event_summary


def _tree(root: Path) -> dict[str, str]:
    return {
        str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(root.rglob("*"))
        if p.is_file()
    }


@pytest.fixture(scope="module")
def scene_copy(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("scene") / "sample"
    shutil.copytree(sample_scene_path(), root)
    return root


@pytest.fixture(scope="module")
def run(scene_copy, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("runs") / "run"
    argv = ["train", str(scene_copy), "--out", str(out), "--iterations", "2", "--scale", "0.25"]
    assert main([*argv, "--no-progress", "--threads", "1"]) == 0
    return out


def test_version(capsys):
    assert main(["--version"]) == 0
    line = capsys.readouterr().out.strip()
    assert line.startswith(f"vadgs {vadgs.__version__} (torch ") and "python 3." in line


def test_train_on_a_folder_of_photos_points_to_sfm(tmp_path, capsys):
    photos = tmp_path / "photos"
    photos.mkdir()
    for i in range(3):
        Image.new("RGB", (32, 24), (10 * i, 0, 0)).save(photos / f"IMG_{i:04d}.JPG")
    before = _tree(tmp_path)
    assert main(["train", str(photos), "--out", str(tmp_path / "run"), "--iterations", "2"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0
    assert (
        f"a folder of 3 photos, not a scene: make a COLMAP project of them first, vadgs sfm {photos}" in err
    )
    assert _tree(tmp_path) == before and not (tmp_path / "run").exists()


def test_eval_of_a_scene_or_project_says_what_it_is(scene_copy, tmp_path, capsys):
    assert main(["eval", str(scene_copy)]) == 2
    err = capsys.readouterr().err
    assert f"RUN {scene_copy}: is a benchmark scene, not a run (no checkpoint.pt): train it first" in err
    from tests.data.colmap_sample import write_sample_colmap

    project = tmp_path / "project"
    write_sample_colmap(project, n_points=50)
    for command in ("eval", "render", "export"):
        assert main([command, str(project)]) == 2
        assert f"RUN {project}: is a COLMAP project, not a run" in capsys.readouterr().err


def test_train_on_a_run_says_it_is_a_run(run, tmp_path, capsys):
    assert main(["train", str(run), "--out", str(tmp_path / "x"), "--iterations", "2"]) == 2
    assert f"SCENE {run}: is a vadgs run, not a scene" in capsys.readouterr().err


def test_eval_names_the_images_and_what_the_fingerprint_checked(run, scene_copy, capsys):
    assert main(["eval", str(run), "--no-progress", "--threads", "1"]) == 0
    out = capsys.readouterr().out
    ev = json.loads((run / "eval.json").read_text())
    scene = load_scene(scene_copy, scale=0.25)
    expected = [str(Path(scene.views[v].image).relative_to(scene_copy)) for v in scene.test_views]
    assert [pv["image"] for pv in ev["per_view"]] == expected
    assert [pv["view"] for pv in ev["per_view"]] == list(scene.test_views)
    assert ev["scene"]["fingerprint_checks"].startswith("the metadata files and the test views'")
    assert f"scene checked: {scene_copy} (fingerprint {ev['scene']['fingerprint']}: the metadata" in out


@pytest.mark.parametrize("which", ["test", "train"])
def test_a_changed_image_of_the_same_size_is_refused(run, scene_copy, tmp_path, capsys, which):
    """R1: an image replaced by another of the same byte size was scored without a word."""
    copy = tmp_path / "scene"
    shutil.copytree(scene_copy, copy)
    scene = load_scene(copy, scale=0.25)
    view = scene.test_views[0] if which == "test" else scene.train_views[0]
    image = Path(scene.views[view].image)
    data = bytearray(image.read_bytes())
    data[len(data) // 2] ^= 0xFF  # the same size, other bytes
    image.write_bytes(bytes(data))
    ref = {**load_checkpoint(run).scene_ref, "path": str(copy)}
    assert scene_fingerprint(ref, open_scene(ref)) != scene_fingerprint(
        {**ref, "path": str(scene_copy)}, open_scene({**ref, "path": str(scene_copy)})
    )
    before = _tree(run)
    assert main(["eval", str(run), "--scene", str(copy), "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert f"scene {copy} (fingerprint " in err and "another scene or changed files" in err
    assert _tree(run) == before
    # the untouched copy is the run's scene wherever it lies
    shutil.copy2(scene_copy / image.relative_to(copy), image)
    assert main(["eval", str(run), "--scene", str(copy), "--no-progress"]) == 0


def test_scale_gives_the_pixel_size(scene_copy, tmp_path, capsys):
    out = tmp_path / "run"
    argv = ["train", str(scene_copy), "--out", str(out), "--iterations", "1", "--scale", "0.25"]
    assert main([*argv, "--no-progress"]) == 0
    assert "resolution: 60x36 (--scale 0.25 of 240x144: as given)" in capsys.readouterr().out


def test_psnr_star_none_is_explained():
    metrics = {
        "steps": 10,
        "train_s": 3.0,
        "num_gaussians": 100,
        "test": {"psnr": 20.0, "psnr_star": None, "ssim": 0.5, "depth": {}},
    }
    assert "PSNR* n/a (no moving-object pixels in the test views)" in metrics_summary(metrics)
    metrics["gaussians_per_node"] = {"static": 90, "track_3": 10}  # a moving object, none in the views
    assert "PSNR* n/a (no moving-object pixels in the test views)" in metrics_summary(metrics)
    metrics["gaussians_per_node"] = {"static": 100}  # no moving object (photos): PSNR* is left out
    assert "test PSNR 20.00 dB, SSIM 0.500" in metrics_summary(metrics)
    assert "PSNR*" not in metrics_summary(metrics)
    metrics["test"]["psnr_star"] = 18.123
    assert "PSNR* 18.12 dB" in metrics_summary(metrics)


def test_event_summary_counts_the_instances_that_added_nothing():
    instances = [
        {"instance": 3, "class": "sign", "added": 120, "reason": "ok"},
        {"instance": 7, "class": "car", "added": 0, "reason": "explained"},
        {"instance": 9, "class": "building", "added": 0, "reason": "selection:no_voxels"},
        {"instance": 11, "class": "building", "added": 0, "reason": "no_consistent_pixels"},
    ]
    entry = {
        "flagged_instances": 4,
        "attempted": 4,
        "repaired": 1,
        "added": 120,
        "skipped": {},
        "total_s": 1.0,
        "instances": instances,
    }
    line = event_summary(entry, VisibilityDensifyConfig())
    assert (
        "4 attempted, 1 repaired (+120 Gaussians), 3 added nothing (car 7: explained; "
        "building 9: selection:no_voxels; building 11: no_consistent_pixels), skipped: none" in line
    )
    entry["instances"] = instances[:1]
    entry["attempted"] = 1
    assert "1 repaired (+120 Gaussians), skipped: none" in event_summary(entry, VisibilityDensifyConfig())
