from __future__ import annotations

import json

from vadgs.cli import main


class TestCli:
    def test_train_eval_render_resume(self, tmp_path, capsys):
        out = tmp_path / "run"
        args = ["train", "--sample", "--scale", "0.25", "--out", str(out), "--iterations", "3"]
        args += ["--no-progress", "--set", "init.max_points=400", "--set", "init.voxel_size=1.0"]
        args += ["--set", "init.sh_degree=0"]
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
        assert main(["train", "--sample", "--out", str(tmp_path / "x"), "--set", "bogus=1"]) == 2

    def test_train_with_vad_strategy(self, tmp_path):
        out = tmp_path / "vad"
        # 18 training views: the first visibility-aware event runs after 5 cycles (step 89), before
        # the last 10% of the iterations (last_event_fraction)
        args = ["train", "--sample", "--scale", "0.25", "--out", str(out), "--iterations", "100", "--vad"]
        args += ["--no-progress", "--set", "init.max_points=2000", "--set", "init.sh_degree=0"]
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


def test_every_train_flag_has_a_resume_policy():
    """A ``vadgs train`` flag is refused on ``--resume``, applied to the resumed run, or of the session.

    Otherwise it would be silently ignored when a run is resumed.
    """
    import argparse

    from vadgs.cli import _NOT_ON_RESUME, _ON_RESUME, _SESSION, _train_args
    from vadgs.train.checkpoint import RESUMABLE_CHANGES

    p = argparse.ArgumentParser()
    _train_args(p)
    flags = {a.dest for a in p._actions} - {"help"}
    refused = {key for key, _ in _NOT_ON_RESUME}
    assert not refused & set(_ON_RESUME) and not refused & set(_SESSION)
    assert flags == refused | set(_ON_RESUME) | set(_SESSION), sorted(
        flags ^ (refused | set(_ON_RESUME) | set(_SESSION))
    )
    assert set(_ON_RESUME) <= set(RESUMABLE_CHANGES)  # what the checkpoint lets a resume change
