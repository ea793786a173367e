from __future__ import annotations

import json

from vadgs.cli import main


class TestCli:
    def test_train_eval_render_resume(self, tmp_path, capsys):
        out = tmp_path / "run"
        args = ["train", "--sample", "--scale", "0.25", "--out", str(out), "--iterations", "3"]
        args += ["--no-progress", "--init.max-points", "400", "--init.voxel-size", "1.0"]
        args += ["--init.sh-degree", "0"]
        assert main(args) == 0
        metrics = json.loads((out / "metrics.json").read_text())
        assert metrics["steps"] == 3 and metrics["test"]["num_views"] == 6
        assert (out / "ply" / "static.ply").is_file() and (out / "ply" / "poses.json").is_file()
        assert main(["eval", str(out), "--no-progress"]) == 0
        assert "psnr" in json.loads((out / "eval.json").read_text())
        assert main(["render", str(out), "--views", "2", "--no-progress"]) == 0
        assert len(list((out / "renders").glob("*.png"))) == 1
        assert main(["train", "--out", str(out), "--resume", "--no-progress"]) == 0  # already complete
        assert "resuming" in capsys.readouterr().out

    def test_bad_inputs(self, tmp_path, capsys):
        (tmp_path / "checkpoint.pt").write_bytes(b"garbage")
        assert main(["eval", str(tmp_path)]) == 2
        assert "corrupt" in capsys.readouterr().err
        assert main(["train", "--out", str(tmp_path / "none"), "--resume"]) == 2
        assert main(["train", "--sample", "--out", str(tmp_path / "x"), "--bogus", "1"]) == 2

    def test_train_with_vad_strategy(self, tmp_path):
        out = tmp_path / "vad"
        # 18 training views: the first visibility-aware event runs after 5 cycles (step 89), before
        # the last 10% of the iterations (last_event_fraction)
        args = ["train", "--sample", "--scale", "0.25", "--out", str(out), "--iterations", "100", "--vad"]
        args += ["--no-progress", "--init.max-points", "2000", "--init.sh-degree", "0"]
        assert main(args) == 0
        ckpt_cfg = json.loads((out / "config.json").read_text())["config"]
        assert ckpt_cfg["vad"]["view_selection"] is True  # the strategy is part of the run's config
        events = json.loads((out / "metrics.json").read_text())["vad_events"]
        assert len(events) == 1 and events[0]["step"] == 89 and events[0]["tested"] > 0
        logged = [json.loads(line) for line in (out / "log.jsonl").read_text().splitlines()]
        logged = [e for e in logged if "event" in e]  # written as it happens, not only at the end
        assert [e["step"] for e in logged] == [90]  # the line of the step that ran the event
        assert logged[0]["event"]["added"] == events[0]["added"]
        assert main(["train", "--out", str(out), "--resume", "--no-progress"]) == 0


def test_every_train_flag_has_a_resume_policy(tmp_path, capsys):
    """On ``--resume`` every ``vadgs train`` flag is of the session, applied, or refused by name.

    Otherwise it would be silently ignored when a run is resumed. Each flag is tried on a real
    checkpoint: the run's own flags (``--scale``, ``--vad``, ...) and every TrainConfig field
    outside ``RESUMABLE_CHANGES`` are refused naming the flag; the resumable ones are applied.
    """
    import dataclasses

    import pytest

    from vadgs.cli.train import SESSION_FIELDS, TrainCommand, parse_train, resume_changes
    from vadgs.train.checkpoint import RESUMABLE_CHANGES
    from vadgs.train.config import TrainConfig

    out = tmp_path / "run"
    args = ["train", "--sample", "--scale", "0.25", "--out", str(out), "--iterations", "1", "--no-progress"]
    assert main([*args, "--init.max-points", "200", "--init.sh-degree", "0"]) == 0
    stored = parse_train(["--out", str(out), "--resume"])
    assert stored.train.iterations == 1 and stored.train.init.max_points == 200  # the checkpoint's
    assert resume_changes(stored, out) == {}
    # SCENE on --resume is where a moved scene is now (checked by its fingerprint: test_run_scene.py)
    others = {
        "sample": True, "config": "c.json", "overwrite": True, "scale": 0.5, "dgp": True,
        "cameras": "a", "test_frames": (1,), "colmap_scene": True, "images": "i", "test_every": 2,
        "no_normalize": True, "colmap": "m", "vad": True, "appearance": True,
    }  # fmt: skip
    fields = {f.name for f in dataclasses.fields(TrainCommand)}
    assert fields == set(others) | set(SESSION_FIELDS), sorted(fields ^ (set(others) | set(SESSION_FIELDS)))
    for name, value in others.items():
        flag = "--" + name.replace("_", "-")
        with pytest.raises(ValueError, match=f"--resume: {flag} cannot be honoured"):
            resume_changes(dataclasses.replace(stored, **{name: value}), out)
    changed = {"iterations": 5, "max_minutes": 1.0, "device": "cpu:0", "threads": 1, "cache_gb": 0.5,
               "checkpoint_every": 7, "checkpoint_minutes": 2.0, "log_every": 3}  # fmt: skip
    assert set(changed) == set(RESUMABLE_CHANGES)
    for name, value in changed.items():
        cmd = dataclasses.replace(stored, train=dataclasses.replace(stored.train, **{name: value}))
        assert resume_changes(cmd, out) == {name: value}
    cmd = dataclasses.replace(stored, train=dataclasses.replace(stored.train, seed=3))
    with pytest.raises(ValueError, match="--seed cannot be honoured"):
        resume_changes(cmd, out)
    for name, value in (("hard_every", 2), ("lambda_hard", 0.5)):
        geometry = dataclasses.replace(stored.train.geometry, **{name: value})
        cmd = dataclasses.replace(stored, train=dataclasses.replace(stored.train, geometry=geometry))
        flag = r"--geometry\." + name.replace("_", "-")
        with pytest.raises(ValueError, match=flag + " cannot be honoured"):
            resume_changes(cmd, out)
    strategy = dataclasses.replace(stored.train.strategy, max_gaussians=5)
    with pytest.raises(ValueError, match=r"--strategy\.max-gaussians cannot be honoured"):
        resume_changes(
            dataclasses.replace(stored, train=dataclasses.replace(stored.train, strategy=strategy)), out
        )
    assert TrainConfig.from_dict(stored.train.to_dict()) == stored.train
    # end to end: a refused flag is one line, exit 2; a resumable one is applied with a note
    assert main(["train", "--out", str(out), "--resume", "--seed", "3"]) == 2
    assert "--resume: --seed cannot be honoured" in capsys.readouterr().err
    assert main(["train", "--out", str(out), "--resume", "--iterations", "2", "--no-progress"]) == 0
    assert "NOTE: --iterations changes the run from 1 to 2" in capsys.readouterr().out
