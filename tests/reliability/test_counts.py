"""Issue 39 item 4: every count a user types is bounded before work starts; videos are streamed.

Each case goes through the CLI as a user would: exit code 2, one line naming the flag, the limit
and the value, and nothing written (the folder hashed before and after).
"""

from __future__ import annotations

import hashlib
import tracemalloc
from pathlib import Path

import numpy as np
import pytest

from vadgs.cli import main
from vadgs.train.results.video import VIDEO_SUFFIXES, check_video_path, write_video

pytest.importorskip("imageio_ffmpeg")

TINY = ["--scale", "0.25", "--no-progress", "--init.max-points", "300", "--init.voxel-size", "1.0"]
TINY += ["--init.sh-degree", "0"]


@pytest.fixture(scope="module")
def run(tmp_path_factory) -> Path:
    """A 1-step run of the sample (60x36 images)."""
    root = tmp_path_factory.mktemp("counts")
    assert (
        main(["--threads", "1", "train", "--sample", "--out", str(root / "run"), "--iterations", "1", *TINY])
        == 0
    )
    return root / "run"


def _tree_hash(folder: Path) -> str:
    """Names and contents of every file under ``folder``."""
    h = hashlib.sha256()
    for p in sorted(folder.rglob("*")):
        h.update(str(p.relative_to(folder)).encode())
        if p.is_file():
            h.update(p.read_bytes())
    return h.hexdigest()


def _one_line(capsys) -> str:
    err = capsys.readouterr().err
    assert "Traceback" not in err
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    return lines[0]


LONG = "a" * 300 + ".mp4"

CASES = [
    (
        ["--video", "{run}/v.mp4", "--trajectory", "orbit:100000000"],
        "--trajectory orbit:100000000: expected at most 100000 frames (--max-frames raises it), "
        "got 100000000",
    ),
    (
        ["--video", "{run}/v.mp4", "--frames-between", "100000000"],
        "--frames-between 100000000: expected at most 100000 frames (--max-frames raises it), got 100000000",
    ),
    (  # each count below the bound, their product over it (8 frames of the sample)
        ["--video", "{run}/v.mp4", "--frames-between", "20000"],
        "--trajectory ego --frames-between 20000: expected at most 100000 frames (--max-frames raises it), "
        "got 140008",
    ),
    (
        ["--video", "{run}/v.mp4", "--trajectory", "orbit:5", "--max-frames", "4"],
        "--trajectory orbit:5: expected at most 4 frames (--max-frames raises it), got 5",
    ),
    (["--video", "{run}/v.mp4", "--trajectory", "orbit:" + "9" * 5000], "expected at most 100000 frames"),
    (["--video", "{run}/v.mp4", "--max-frames", "0"], "--max-frames: expected an integer >= 1, got 0"),
    (
        ["--video", "{run}/v.mp4", "--trajectory", "shift:nan"],
        "--trajectory: expected finite metres in shift:METRES or shift:X,Y,Z, got 'shift:nan'",
    ),
    (["--video", "{run}/v.mp4", "--trajectory", "shift:inf"], "--trajectory: expected finite metres"),
    (["--video", "{run}/v.mp4", "--trajectory", "shift:0,-inf,0"], "got 'shift:0,-inf,0'"),
    (
        ["--video", "{run}/v.xyz"],
        "--video {run}/v.xyz: expected a video name ending in .mp4, .mov or .mkv, got suffix '.xyz'",
    ),
    (
        ["--video", "{run}/v"],
        "--video {run}/v: expected a video name ending in .mp4, .mov or .mkv, got no suffix",
    ),
    (
        ["--video", "{run}/"],
        "--video {run}/: expected a video file name ending in .mp4, .mov or .mkv, got a folder",
    ),
    (
        ["--video", "{run}/" + LONG],
        "--video {run}/"
        + LONG
        + ": expected a file name of at most 241 bytes (the file system's 255 less 14 "
        "for the temporary file), got 304",
    ),
    (
        ["--video", "{run}/config.json/v.mp4"],
        "--video {run}/config.json: expected a folder, got an existing file",
    ),
    (["--threads", "100000000"], "--threads: expected an integer in [0, 1024], got 100000000"),
]


class TestRenderCounts:
    @pytest.mark.parametrize("flags, line", CASES, ids=[" ".join(c[0])[-40:] for c in CASES])
    def test_refused_before_work(self, run, flags, line, capsys):
        before = _tree_hash(run)
        argv = ["render", str(run), "--no-progress", *(f.format(run=run) for f in flags)]
        assert main(argv) == 2
        got = _one_line(capsys)
        assert got.startswith("vadgs render: error: "), got
        assert line.format(run=run) in got, got
        assert _tree_hash(run) == before  # nothing written, no temporary file left
        assert not any(run.parent.glob("*.mp4"))

    def test_max_frames_raises_the_bound(self, run, capsys):
        out = run.parent / "orbit5.mp4"
        assert (
            main(["render", str(run), "--no-progress", "--video", str(out), "--trajectory", "orbit:5"]) == 0
        )
        assert "5 frames" in capsys.readouterr().out and out.is_file()
        out.unlink()

    def test_a_path_far_from_the_scene_warns(self, run, capsys):
        out = run.parent / "far.mp4"
        assert (
            main(["render", str(run), "--no-progress", "--video", str(out), "--trajectory", "shift:1e30"])
            == 0
        )
        line = _one_line(capsys)
        assert line.startswith(
            "vadgs render: warning: --trajectory shift:1e30: no Gaussian in view of any of its 8"
        )
        out.unlink()
        assert (
            main(["render", str(run), "--no-progress", "--video", str(out), "--trajectory", "shift:2"]) == 0
        )
        assert capsys.readouterr().err == ""  # a lane change sees the scene: no warning
        out.unlink()

    def test_view_port_bounded(self, run, capsys):
        assert main(["view", str(run), "--port", "70000"]) == 2
        assert _one_line(capsys) == "vadgs view: error: --port: expected an integer in [1, 65535], got 70000"


class TestCheckVideoPath:
    @pytest.mark.parametrize("suffix", VIDEO_SUFFIXES)
    def test_supported(self, suffix):
        assert check_video_path("a/b" + suffix) == Path("a/b" + suffix)

    def test_name_of_241_bytes_passes_242_fails(self):
        check_video_path("d/" + "é" * 118 + "a.mp4")  # 236 + 1 + 4 bytes
        with pytest.raises(ValueError, match="got 242"):
            check_video_path("d/" + "é" * 118 + "ab.mp4")


class TestStreamedVideo:
    """The frames go to the encoder one by one: peak memory does not grow with the video's length."""

    @staticmethod
    def _peak(path: Path, n: int) -> int:
        def frames():
            for i in range(n):
                yield np.full((64, 96, 3), i % 256, dtype=np.uint8)  # 18 KB each

        tracemalloc.start()
        try:
            count, size = write_video(path, frames(), fps=10, progress=False)
            peak = tracemalloc.get_traced_memory()[1]
        finally:
            tracemalloc.stop()
        assert (count, size) == (n, (64, 96)) and path.is_file()
        return peak

    def test_peak_memory_does_not_grow_with_frames(self, tmp_path):
        self._peak(tmp_path / "warm.mp4", 2)  # imports and ffmpeg's first start outside the measure
        short, long = self._peak(tmp_path / "a.mp4", 20), self._peak(tmp_path / "b.mp4", 200)
        # a list of the frames would hold 180 x 18 KB = 3.3 MB more
        assert long - short < 1_000_000, (short, long)

    def test_render_video_through_the_cli(self, run):
        """Rendering too: 200 frames of the tiny run take no more memory than 20."""
        peaks = []
        for n in (2, 20, 200):  # the first loads modules and starts ffmpeg outside the measure
            out = run.parent / f"o{n}.mp4"
            argv = ["render", str(run), "--no-progress", "--video", str(out), "--trajectory", f"orbit:{n}"]
            tracemalloc.start()
            try:
                assert main(argv) == 0
                peaks.append(tracemalloc.get_traced_memory()[1])
            finally:
                tracemalloc.stop()
            out.unlink()
        # a list of the frames would hold 180 x 22 KB = 3.9 MB more
        assert peaks[2] - peaks[1] < 1_000_000, peaks

    def test_a_failed_video_leaves_no_file(self, tmp_path):
        def frames():
            yield np.zeros((8, 8, 3), dtype=np.uint8)
            raise RuntimeError("stop")

        with pytest.raises(RuntimeError, match="stop"):
            write_video(tmp_path / "v.mp4", frames(), progress=False)
        assert list(tmp_path.iterdir()) == []


class TestTrajectoryLength:
    """The library's bound: counted before a pose is built, the same errors as make_trajectory."""

    def test_counts_without_building(self, tiny_scene):
        from vadgs.train.results.trajectory import make_trajectory, trajectory_length

        for spec, between in [
            ("ego", 3),
            ("shift:2", None),
            ("interpolate", 2),
            ("orbit:7", None),
            ("orbit", None),
        ]:
            n = trajectory_length(tiny_scene, spec, frames_between=between)
            assert n == len(make_trajectory(tiny_scene, spec, frames_between=between).time)
        assert trajectory_length(tiny_scene, "orbit:" + "9" * 5000) == 10**18
        assert trajectory_length(tiny_scene, "orbit:" + "0" * 30 + "5") == 5

    def test_max_frames(self, tiny_scene):
        from vadgs.train.results.trajectory import make_trajectory

        with pytest.raises(ValueError, match=r"max_frames: expected at most 4 frames, got 5 \(orbit:5\)"):
            make_trajectory(tiny_scene, "orbit:5", max_frames=4)
        assert len(make_trajectory(tiny_scene, "orbit:5", max_frames=None).time) == 5
        with pytest.raises(ValueError, match="expected finite metres"):
            make_trajectory(tiny_scene, "shift:1,nan,0")
