"""examples/photos_to_video.sh end to end on the 10-photo room (three sizes, one photo sideways):
SfM, VAD-GS training with events, evaluation, a video along the photos' cameras, the export."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import imageio.v2 as imageio
import pytest

from ..data.photo_sample import write_photo_set

pytest.importorskip("pycolmap")
REPO = Path(__file__).resolve().parents[2]
SCRIPT = REPO / "examples" / "photos_to_video.sh"


def _run(photos: Path, out: Path, *flags: str, **env: str) -> subprocess.CompletedProcess:
    env = {
        **os.environ,
        "PYTHONPATH": str(REPO),
        "VADGS": f"{sys.executable} -m vadgs.cli",
        "THREADS": "1",
        "NO_PROGRESS": "1",
        **env,
    }
    return subprocess.run(
        ["bash", str(SCRIPT), str(photos), str(out), *flags], env=env, capture_output=True, text=True
    )


def test_photos_to_video(tmp_path):
    truth = write_photo_set(tmp_path / "photos")
    out = tmp_path / "castle"
    # 16 steps at half resolution, a VAD-GS event after every cycle of the 8 training photos
    proc = _run(tmp_path / "photos", out, "--scale", "0.5", "--vad.every-cycles", "1", ITERATIONS="16")
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-2000:]
    said = proc.stdout
    assert "registered 10 of 10 photos" in said and "== step 5/5" in said and "Traceback" not in proc.stderr
    assert said.startswith(f"10 photos in {tmp_path / 'photos'}; 16 training steps. Times measured")
    project, run = out / "project", out / "run"
    assert sorted(p.name for p in (project / "images").iterdir()) == truth["names"]
    metrics = json.loads((run / "metrics.json").read_text())
    assert metrics["steps"] == 16 and metrics["test"]["num_views"] == 2  # photos 0 and 8 held out
    evaluated = json.loads((run / "eval.json").read_text())
    assert evaluated["psnr"] == pytest.approx(metrics["test"]["psnr"], abs=1e-3)
    events = [
        json.loads(line)["event"]
        for line in (run / "log.jsonl").read_text().splitlines()
        if '"event"' in line
    ]
    assert events and sum(e["repaired"] for e in events) >= 1  # VAD-GS ran and added Gaussians
    # the video: the interpolated path through the 8 training photos, 8 poses between each
    assert "(trajectory interpolate, camera camera_1)" in said
    with imageio.get_reader(run / "video.mp4", format="FFMPEG") as reader:
        frames = [f for f in reader]
    assert len(frames) == 7 * 9 + 1 and frames[0].std() > 5
    # the export: one PLY of every Gaussian
    ply = run / "export" / "frame000" / "world_frame000.ply"
    header = ply.read_bytes()[:2000].split(b"end_header")[0].decode()
    assert f"element vertex {metrics['num_gaussians']}" in header
    # again without OVERWRITE=1: the first step refuses, naming the flag, and the script stops
    again = _run(tmp_path / "photos", out, ITERATIONS="16")
    assert again.returncode == 2 and "--overwrite replaces them" in again.stderr
    assert "== step 2/5" not in again.stdout
