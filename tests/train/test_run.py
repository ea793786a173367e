"""vadgs.train.run: a run folder's bookkeeping and its finish (evaluate, export, metrics.json once)."""

from __future__ import annotations

import dataclasses
import json
import time

from vadgs.io import TMP_GLOB
from vadgs.train.checkpoint import clear_run, describe_run
from vadgs.train.run import finish_run
from vadgs.train.trainer import Trainer


def test_finish_run_writes_the_metrics_it_returns(tiny_scene, tiny_config, tmp_path):
    config = dataclasses.replace(tiny_config, iterations=4, checkpoint_every=4)
    trainer = Trainer(tiny_scene, config, out_dir=tmp_path, progress=False)
    result = trainer.train()
    assert describe_run(tmp_path) == "step 4/4"
    t0 = time.perf_counter()
    metrics = finish_run(trainer, tmp_path, result, progress=False, started=t0)
    on_disk = json.loads((tmp_path / "metrics.json").read_text())
    assert on_disk == json.loads(json.dumps(metrics, default=str))
    assert on_disk["steps"] == 4 and on_disk["num_gaussians"] == trainer.model.num_gaussians
    assert 0 < on_disk["wall_s"] <= time.perf_counter() - t0 + 0.1
    # the test views were evaluated: one entry per held-out view, a real PSNR
    per_view = on_disk["test"]["per_view"]
    assert [p["view"] for p in per_view] == tiny_scene.test_views and all(p["psnr"] > 5 for p in per_view)
    assert sorted(p.name for p in (tmp_path / "ply").glob("*.ply"))  # the export
    assert "vad_events" not in on_disk  # standard densification
    assert list(tmp_path.glob(TMP_GLOB)) == []
    removed = clear_run(tmp_path)
    # the files it wrote (recorded in its manifest), not whole folders; the emptied ply/ goes too
    assert {p.name for p in removed} >= {"checkpoint.pt", "metrics.json", "static.ply", "poses.json"}
    assert describe_run(tmp_path) is None and not (tmp_path / "ply").exists()


def test_load_run_gives_back_the_trained_model(tiny_scene, tiny_config, tmp_path):
    import pytest
    import torch

    from vadgs.train.run import frame_position, load_run

    config = dataclasses.replace(tiny_config, iterations=3, checkpoint_every=3)
    ref = {"kind": "benchmark", "path": str(tiny_scene.root), "scale": 0.25}
    trainer = Trainer(tiny_scene, config, out_dir=tmp_path, progress=False, scene_ref=ref)
    trainer.train()
    run = load_run(tmp_path)
    assert run.step == 3 and run.config == config and run.appearance is None
    for k, v in trainer.model.params.items():
        assert torch.equal(run.model.params[k], v), k
    assert run.scene.name == tiny_scene.name and run.scene.num_views == tiny_scene.num_views
    assert load_run(tmp_path / "checkpoint.pt", open=False).scene is None
    first = tiny_scene.frames[0].index
    assert frame_position(run.scene, None) == (first, 0)
    assert frame_position(run.scene, tiny_scene.frames[2].index) == (tiny_scene.frames[2].index, 2)
    with pytest.raises(ValueError, match=r"--frame: scene .* has frames .*, got 999"):
        frame_position(run.scene, 999, "--frame")


def test_scene_ref_finds_the_kind_and_checks_the_options(tmp_path):
    import pytest

    from vadgs.data import sample_scene_path
    from vadgs.train.scenes import BenchmarkRef, ColmapRef, DGPRef, scene_ref

    ref = scene_ref(sample_scene_path(), scale=0.25)
    assert ref == BenchmarkRef(str(sample_scene_path()), 0.25)
    assert ref.to_dict() == {"kind": "benchmark", "path": str(sample_scene_path()), "scale": 0.25}
    assert scene_ref(sample_scene_path() / "scene.json").kind == "benchmark"
    dgp = scene_ref(tmp_path, "dgp", cameras=["front"], test_frames=[3])
    assert dgp == DGPRef(str(tmp_path), 0.5, ("front",), (3,))
    assert dgp.to_dict()["cameras"] == ["front"] and dgp.to_dict()["test_frames"] == [3]
    assert ColmapRef(str(tmp_path)).scale == 1.0  # COLMAP images at full size, the others at half
    with pytest.raises(FileNotFoundError, match=r"neither a benchmark scene .* nor a COLMAP model"):
        scene_ref(tmp_path)
    with pytest.raises(ValueError, match=r"\['images'\]: not options of a benchmark scene"):
        scene_ref(sample_scene_path(), images="x")
    with pytest.raises(ValueError, match="kind: expected one of"):
        scene_ref(tmp_path, "nerf")
    with pytest.raises(ValueError, match=r"scale: expected a finite number > 0, got 0"):
        BenchmarkRef(str(tmp_path), scale=0)
    with pytest.raises(ValueError, match=r"^test_every: expected an integer >= 0 \(0: none held out\)"):
        ColmapRef(str(tmp_path), test_every=-1)


def test_train_scene_is_the_run_a_trainer_does(tiny_scene, tiny_config, tmp_path):
    """train_scene = Trainer + train + finish_run: same parameters, metrics written; resume goes on."""
    import pytest
    import torch

    from vadgs.train.run import load_run, train_scene
    from vadgs.train.scenes import scene_fingerprint, scene_ref

    config = dataclasses.replace(tiny_config, iterations=4, checkpoint_every=2)
    ref = scene_ref(tiny_scene.root, scale=0.25)
    said: list[str] = []
    outcome = train_scene(ref, config, tmp_path / "a", progress=False, log=said.append)
    assert outcome.completed and outcome.reason == "done" and outcome.step == 4
    assert outcome.metrics == json.loads((tmp_path / "a" / "metrics.json").read_text())
    assert any(f"{len(tiny_scene.train_views)} training views" in s for s in said)
    trainer = Trainer(tiny_scene, config, out_dir=tmp_path / "b", progress=False)
    trainer.train()
    run = load_run(tmp_path / "a")
    # the scene by its absolute path, the run folder and the content fingerprint of the scene
    fingerprint = scene_fingerprint(ref.to_dict(), tiny_scene)
    run_dir = str((tmp_path / "a").resolve())
    assert run.checkpoint.scene_ref == {
        **ref.to_dict(),
        "run_dir": run_dir,
        "fingerprint": fingerprint,
    }
    assert run.scene_ref["fingerprint"] == fingerprint and run.scene.num_views == tiny_scene.num_views
    for k, v in trainer.model.params.items():
        assert torch.equal(run.model.params[k], v), k
    assert outcome.metrics["num_gaussians"] == trainer.model.num_gaussians
    # the run folder is not overwritten unless asked; resume continues it with a longer schedule
    with pytest.raises(ValueError, match=r"holds a run \(step 4/4\); use resume=True"):
        train_scene(ref, config, tmp_path / "a", progress=False)
    with pytest.raises(ValueError, match=r"resume=True.*pass None"):
        train_scene(ref, None, tmp_path / "a", resume=True)
    more = train_scene(None, None, tmp_path / "a", resume=True, config_changes={"iterations": 6})
    assert more.completed and more.step == 6 and more.metrics["steps"] == 6
    again = train_scene(ref, config, tmp_path / "a", overwrite=True, progress=False)
    assert again.step == 4 and again.metrics["num_gaussians"] == outcome.metrics["num_gaussians"]


def test_scene_fingerprint_without_file_digest(tiny_scene, monkeypatch):
    """Python 3.10 has no hashlib.file_digest: the fingerprint is the same without it.

    (Found by mypy with python_version 3.10: scene_fingerprint raised AttributeError there.)
    """
    import hashlib
    import io

    from vadgs.train.scenes import file_sha256, scene_fingerprint, scene_ref

    data = bytes(range(256)) * 5000  # more than one block of file_sha256
    fh = io.BytesIO(data)
    fh.seek(7)  # as hashlib.file_digest: from the file's position on
    assert file_sha256(fh) == hashlib.sha256(data[7:]).digest()
    ref = scene_ref(tiny_scene.root, scale=0.25).to_dict()
    expected = scene_fingerprint(ref, tiny_scene)
    monkeypatch.delattr(hashlib, "file_digest", raising=False)
    assert scene_fingerprint(ref, tiny_scene) == expected
