"""benchmarks/per_camera_psnr.py on run folders the test writes."""

from __future__ import annotations

import json
import runpy
import subprocess
import sys
from pathlib import Path

import pytest

SCRIPT = Path(__file__).resolve().parents[1] / "benchmarks" / "per_camera_psnr.py"


def _run(folder: Path, psnrs: dict[str, float]) -> Path:
    folder.mkdir()
    views = [{"view": i, "image": image, "psnr": p} for i, (image, p) in enumerate(psnrs.items())]
    (folder / "metrics.json").write_text(json.dumps({"test": {"per_view": views}}))
    return folder


def test_camera_means_and_differences(tmp_path):
    base = _run(tmp_path / "base", {"images/a/0.png": 30.0, "images/a/4.png": 32.0, "images/b/0.png": 25.0})
    vad = _run(tmp_path / "vad", {"images/a/0.png": 31.5, "images/a/4.png": 32.0, "images/b/0.png": 24.75})
    script = runpy.run_path(str(SCRIPT))
    assert script["camera_means"](script["per_view"](base)) == {"a": 31.0, "b": 25.0}
    out = subprocess.run(
        [sys.executable, str(SCRIPT), str(vad), "--against", str(base)],
        capture_output=True,
        text=True,
        check=True,
    ).stdout.splitlines()
    assert out == [
        f"{vad}: a 31.75 | b 24.75",
        "  images/a/0.png: +1.50 dB",
        "  images/a/4.png: +0.00 dB",
        "  images/b/0.png: -0.25 dB",
    ]


def test_refuses_a_folder_without_metrics(tmp_path):
    with pytest.raises(FileNotFoundError, match=r"run: expected .*metrics.json \(a finished vadgs run\)"):
        runpy.run_path(str(SCRIPT))["per_view"](tmp_path)
