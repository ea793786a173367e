"""The bad-input trial of issue 33, repeated on cases of its own: prints one Markdown table row per case.

Every case builds its faulty input in a temporary folder, runs it (a ``vadgs`` command in a fresh
process, so that a native abort shows as its exit code, or a library call in this process) and
reports the exit code (or the exception type), the time and the first line of the error. The
table is in ``docs/reliability.md`` ("The trial repeated"). Needs the bundled sample scene only;
takes about 5 minutes on 2 cores.

    python tools/reliability_trial.py [--only SUBSTRING] > trial.md
"""

from __future__ import annotations

import argparse
import json
import re
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
import warnings
from collections.abc import Callable
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from tests.data.colmap_sample import write_sample_colmap  # noqa: E402
from tests.data.sample_copy import copy_sample_scene  # noqa: E402

WORK = Path(tempfile.mkdtemp(prefix="vadgs-trial-"))
FAST = ["--no-progress", "--threads", "1", "--iterations", "2", "--init.max-points", "500"]
ROWS: list[tuple[str, str, str, str, str]] = []


def vadgs(*args: str, timeout: float = 600) -> tuple[int, str, str, float]:
    """Run ``python -m vadgs.cli ARGS``: exit code, stdout, stderr, seconds."""
    t0 = time.monotonic()
    res = subprocess.run(
        [sys.executable, "-m", "vadgs.cli", *args], capture_output=True, text=True, timeout=timeout, cwd=ROOT
    )
    return res.returncode, res.stdout, res.stderr, time.monotonic() - t0


def first_error(stderr: str) -> str:
    """The last line of an error output that is not a traceback or warning source line."""
    lines = [ln for ln in stderr.splitlines() if ln.strip() and not ln.startswith(("  warnings.warn", "  "))]
    return lines[-1] if lines else ""


def short(text: str, n: int = 170) -> str:
    """``text`` for a table cell: the temporary folder as ``T``, at most ``n`` characters."""
    text = text.replace(str(WORK), "T").replace("|", "\\|")
    return text if len(text) <= n else text[: n - 1] + "…"


def row(case: str, what: str, outcome: str, seconds: float, message: str) -> None:
    """Record and print one table row."""
    ROWS.append((case, what, outcome, f"{seconds:.1f}", short(message)))
    print(f"| {len(ROWS)} | {case} | {what} | {outcome} | {seconds:.1f} | {short(message)} |", flush=True)


def cli_case(case: str, what: str, args: list[str], after: Callable[[str, str], str] | None = None) -> None:
    """Run a ``vadgs`` command and record its exit code and error (``after`` may pick the message)."""
    code, out, err, s = vadgs(*args)
    message = first_error(err) if code else (out.strip().splitlines() or [""])[-1]
    if code and not message:  # vadgs check: the report's error rows are on stdout
        message = next((ln for ln in out.splitlines() if ln.startswith("error")), out.strip()[-200:])
    if after is not None:
        message = after(out, err) or message
    row(case, what, f"exit {code}", s, message)


def api_case(case: str, what: str, call: Callable[[], object]) -> None:
    """Call the library in this process and record what it raised, warned or returned."""
    t0 = time.monotonic()
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            got = call()
        outcome, message = "returned", repr(got)[:120]
        if caught:
            outcome, message = "warning", str(caught[-1].message)
    except Exception as e:  # the kind of error is the result
        outcome, message = type(e).__name__, " ".join(str(e).split())
    row(case, what, outcome, time.monotonic() - t0, message)


# --------------------------------------------------------------------------------------------------
# scene files


def scene_cases() -> None:
    """Benchmark scenes whose ``scene.json`` names files outside the scene, odd names, deep JSON."""

    def edited(name: str, edit: Callable[[dict, Path], None]) -> Path:
        root = copy_sample_scene(WORK / name)
        meta = json.loads((root / "scene.json").read_text())
        edit(meta, root)
        (root / "scene.json").write_text(json.dumps(meta))
        return root

    def image_outside(meta: dict, root: Path) -> None:
        shutil.copy(root / meta["frames"][0]["views"][0]["image"], root.parent / "outside.png")
        meta["frames"][0]["views"][0]["image"] = "../outside.png"

    root = edited("s1", image_outside)
    cli_case("scene", "`scene.json` image `../outside.png`", ["check", str(root)])
    root = edited("s2", lambda m, r: m["frames"][0].__setitem__("lidar", "/etc/hostname"))
    cli_case("scene", "`scene.json` LiDAR `/etc/hostname` (absolute)", ["check", str(root)])
    root = edited("s3", lambda m, r: m["tracks"][0].__setitem__("mesh", "../../../etc/passwd"))
    cli_case("scene", "`scene.json` track mesh `../../../etc/passwd`", ["check", str(root)])

    root = copy_sample_scene(WORK / "s4")
    meta = json.loads((root / "scene.json").read_text())
    img = root / meta["frames"][0]["views"][0]["image"]
    shutil.move(img, WORK / "s4" / "secret.png")
    img.symlink_to(WORK / "s4" / "secret.png")
    cli_case(
        "scene",
        "an image that is a symlink out of the scene",
        ["check", str(root)],
        lambda out, err: first_error(err.split("warnings.warn")[0]) if "UserWarning" in err else "",
    )

    def rename(meta: dict, root: Path) -> None:
        meta["cameras"]["../../escaped"] = meta["cameras"].pop("front")
        for f in meta["frames"]:
            for v in f["views"]:
                if v["camera"] == "front":
                    v["camera"] = "../../escaped"

    root = edited("s5", rename)
    run = WORK / "s5run"
    code, _, _, s = vadgs("train", str(root), "--out", str(run), "--scale", "0.25", *FAST)
    code2, out2, _, s2 = vadgs("render", str(run), "--threads", "1", "--no-progress")
    escaped = [p for p in WORK.rglob("*escaped*") if run not in p.parents]
    row(
        "scene",
        "camera named `../../escaped`: `train`, then `render` panels",
        f"exit {code}, {code2}",
        s + s2,
        f"{out2.strip()}; files named after it outside the run: {len(escaped)}",
    )
    root = edited("s6", lambda m, r: m["frames"][2]["views"].append(m["frames"][2]["views"][1]))
    cli_case("scene", "a view listed twice in a frame", ["check", str(root)])
    (WORK / "s7").mkdir()
    (WORK / "s7" / "scene.json").write_text('{"cameras": ' + "[" * 100_000 + "]" * 100_000 + "}")
    cli_case("scene", "`scene.json` nested 100,000 deep", ["check", str(WORK / "s7")])
    (WORK / "s8").mkdir()
    (WORK / "s8" / "cfg.json").write_text("[" * 100_000 + "]" * 100_000)
    cli_case(
        "flags",
        "`--config` nested 100,000 deep",
        ["train", "--sample", "--config", str(WORK / "s8" / "cfg.json"), "--out", str(WORK / "s8run")],
    )


# --------------------------------------------------------------------------------------------------
# COLMAP projects


def colmap_cases() -> None:
    """COLMAP projects with unsafe or duplicate names, bad images, poses and truncated files."""
    import pycolmap

    base = WORK / "cbase"
    write_sample_colmap(base, model="OPENCV", k=0.05, n_points=150, crop={"front": (144, 240)})
    text = WORK / "ctext"
    text.mkdir()
    pycolmap.Reconstruction(str(base / "sparse" / "0")).write_text(str(text))

    def variant(name: str, text_model: bool = False) -> Path:
        out = WORK / name
        shutil.copytree(base / "images", out / "images")
        shutil.copytree(text if text_model else base / "sparse" / "0", out / "sparse" / "0")
        return out

    def edit(p: Path, name: str, fn: Callable[[str], str]) -> None:
        f = p / "sparse" / "0" / name
        f.write_text(fn(f.read_text()))

    def train(case: str, what: str, p: Path) -> None:
        run = WORK / f"{p.name}-run"
        code, out, err, s = vadgs("train", str(p), "--out", str(run), *FAST)
        left = sorted(x.name for x in run.iterdir()) if run.is_dir() else []
        message = (
            first_error(err) if code else out.strip().splitlines()[-1]
        ) + f"; left in the run folder: {left}"
        row(case, what, f"exit {code}", s, message)

    p = variant("c1", True)
    (WORK / "victim.png").write_bytes(b"precious")
    edit(p, "images.txt", lambda t: t.replace(" 1 front/016.png", " 1 ../../victim.png"))
    train("COLMAP", "image NAME `../../victim.png` (OPENCV camera)", p)
    p = variant("c2", True)
    edit(p, "images.txt", lambda t: t.replace(" 1 front/016.png", " 1 /tmp/x.png"))
    train("COLMAP", "image NAME `/tmp/x.png`", p)
    p = variant("c3", True)
    edit(p, "images.txt", lambda t: t.replace(" 3 front_right/016.png", " 3 front/016.png"))
    train("COLMAP", "two images named `front/016.png`", p)
    p = variant("c4")
    from PIL import Image

    Image.new("RGB", (239, 144)).save(p / "images" / "front_left" / "018.png")
    train("COLMAP", "one image 1 pixel narrower than its OPENCV camera", p)
    p = variant("c5")
    f = p / "images" / "front" / "019.png"
    f.write_bytes(f.read_bytes()[:3000])
    train("COLMAP", "truncated PNG under an OPENCV camera", p)
    p = variant("c6")
    (p / "images" / "front" / "020.png").write_bytes(b"")
    train("COLMAP", "0-byte image under an OPENCV camera", p)
    p = variant("c7")
    (p / "images" / "front" / "021.png").write_bytes(b"not an image at all" * 100)
    train("COLMAP", "garbage bytes as an image", p)
    p = variant("c8", True)
    edit(p, "frames.txt", lambda t: re.sub(r"^2 2 \S+ \S+ \S+ \S+ ", "2 2 0 0 0 0 ", t, flags=re.M))
    train("COLMAP", "zero quaternion in `frames.txt`", p)
    p = variant("c9", True)
    edit(p, "frames.txt", lambda t: re.sub(r"^2 2 (\S+ \S+ \S+ \S+) \S+ ", r"2 2 \1 inf ", t, flags=re.M))
    train("COLMAP", "`inf` translation in `frames.txt`", p)
    p = variant("c10", True)
    edit(p, "frames.txt", lambda t: re.sub(r"^2 2 \S+ \S+ \S+ \S+ ", "2 2 2 0 0 0 ", t, flags=re.M))
    train("COLMAP", "quaternion of norm 2 in `frames.txt`", p)
    for name in ("points3D", "images", "cameras"):
        p = variant(f"c11{name}")
        f = p / "sparse" / "0" / f"{name}.bin"
        f.write_bytes(f.read_bytes()[: f.stat().st_size * 2 // 3])
        train("COLMAP", f"`{name}.bin` cut to 2/3", p)
    p = variant("c12")
    f = p / "sparse" / "0" / "images.bin"
    f.write_bytes(f.read_bytes() + b"\0" * 13)
    train("COLMAP", "13 bytes of garbage after `images.bin`", p)
    p = variant("c13", True)
    edit(p, "cameras.txt", lambda t: re.sub(r"^1 OPENCV 240 144", "1 OPENCV 0 144", t, flags=re.M))
    train("COLMAP", "camera of width 0 in `cameras.txt`", p)
    p = variant("c14", True)
    edit(
        p,
        "points3D.txt",
        lambda t: re.sub(r"^(\d+ (?:\S+ ){7})(\d+) ", r"\g<1>9999 ", t, count=1, flags=re.M),
    )
    train("COLMAP", "a track observing image 9999 (not in the model) in `points3D.txt`", p)


# --------------------------------------------------------------------------------------------------
# flags


def flag_cases() -> None:
    """``vadgs train`` flags out of range, ``--out`` where nothing can be written, ``--threads``."""
    out = ["--out", str(WORK / "frun")]
    for flags, what in [
        (["--lr.means", "nan"], "`--lr.means nan`"),
        (["--lr.sh-rest", "-1e-3"], "`--lr.sh-rest -1e-3`"),
        (["--geometry.lambda-soft", "inf"], "`--geometry.lambda-soft inf`"),
        (["--ssim-weight", "1.5"], "`--ssim-weight 1.5`"),
        (["--geometry.hard-until", "-0.1"], "`--geometry.hard-until -0.1`"),
        (["--iterations", "0"], "`--iterations 0`"),
        (["--scale", "1e6"], "`--scale 1e6`"),
        (["--scale", "1e-7"], "`--scale 1e-7`"),
        (["--init.voxel-size", "1e-30"], "`--init.voxel-size 1e-30`"),
        (["--init.max-scale", "inf"], "`--init.max-scale inf`"),
        (["--diverge-share", "nan"], "`--diverge-share nan`"),
    ]:
        cli_case("flags", what, ["train", "--sample", *out, *flags, "--no-progress"])
    cli_case("flags", "`--out /proc/vadgs/run` (as root)", ["train", "--sample", "--out", "/proc/vadgs/run"])
    cli_case("flags", "`--out /sys/run` (as root)", ["train", "--sample", "--out", "/sys/run"])
    run = WORK / "trun"
    code, _, _, s = vadgs("train", "--sample", "--out", str(run), "--scale", "0.25", *FAST)
    threads = json.loads((run / "metrics.json").read_text())["threads"] if code == 0 else None
    row("flags", "`--threads 1`: `metrics.json` threads", f"exit {code}", s, f'"threads": {threads}')


# --------------------------------------------------------------------------------------------------
# the viewer


def viewer_cases() -> None:
    """``vadgs view``: the address it listens on, SIGTERM."""
    run = WORK / "trun"
    for extra, what in [([], "`vadgs view RUN`, then SIGTERM"), (["--host", "0.0.0.0"], "`--host 0.0.0.0`")]:
        with socket.socket() as sock:
            sock.bind(("127.0.0.1", 0))
            port = sock.getsockname()[1]
        t0 = time.monotonic()
        proc = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "vadgs.cli",
                "--threads",
                "1",
                "view",
                str(run),
                "--port",
                str(port),
                *extra,
            ],
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
            cwd=ROOT,
        )
        line = ""
        while not line.startswith("open") and proc.poll() is None:
            line = proc.stdout.readline()
        proc.send_signal(signal.SIGTERM)
        rest, _ = proc.communicate(timeout=60)
        stack = "Traceback" in rest or "Fatal" in rest
        row(
            "viewer",
            what,
            f"exit {proc.returncode}",
            time.monotonic() - t0,
            f"{line.strip()}; traceback after SIGTERM: {stack}",
        )


# --------------------------------------------------------------------------------------------------
# the Python API


def api_cases() -> None:
    """Library calls with values out of range."""
    from tests.mvs.mvs_scenes import plane_scene
    from vadgs.data import load_scene, sample_scene_path
    from vadgs.geometry import invert_rigid, project_points, quaternion_to_rotation
    from vadgs.geometry.rotation import normals_to_quats
    from vadgs.geometry.voxel import voxelize
    from vadgs.mvs import PatchMatchConfig, patchmatch
    from vadgs.mvs.planar import fit_plane_ransac
    from vadgs.select import max_weight_clique, top_k_views

    nan = float("nan")
    api_case(
        "API",
        "`max_weight_clique` n=40, k=10 (complete graph)",
        lambda: max_weight_clique(torch.rand(40), torch.rand(40, 40), 10),
    )
    adj = torch.ones(60, 60, dtype=torch.bool)
    for i in range(0, 60, 3):
        adj[i : i + 3, i : i + 3] = False
    api_case(
        "API",
        "`max_weight_clique` on a graph of 3^20 maximal cliques",
        lambda: max_weight_clique(torch.rand(60), torch.rand(60, 60), 4, adj),
    )
    api_case(
        "API",
        "`max_weight_clique` n=24, k=4 (the selector's default)",
        lambda: max_weight_clique(torch.rand(24), torch.rand(24, 24), 4).nodes.tolist(),
    )
    api_case(
        "API",
        "`max_weight_clique` with an infinite edge weight",
        lambda: max_weight_clique(torch.ones(3), torch.full((3, 3), float("inf")), 2),
    )
    api_case(
        "API",
        "`invert_rigid` of a (2, 4, 4) with one zero matrix",
        lambda: invert_rigid(torch.stack([torch.eye(4), torch.zeros(4, 4)])),
    )
    api_case(
        "API",
        "`project_points` with fy = -100",
        lambda: project_points(
            torch.ones(1, 1, 3), torch.tensor([[[100.0, 0, 5], [0, -100.0, 5], [0, 0, 1]]])
        ),
    )
    api_case(
        "API",
        "`quaternion_to_rotation` with one NaN quaternion",
        lambda: quaternion_to_rotation(torch.tensor([[1.0, 0, 0, 0], [nan, 0, 0, 0]])),
    )
    sc = plane_scene()
    api_case(
        "API",
        "`patchmatch` with float64 K, float32 images",
        lambda: patchmatch(
            sc.image,
            sc.src_images,
            sc.K.double(),
            sc.src_K,
            sc.world_to_cam,
            sc.src_world_to_cam,
            (1.0, 10.0),
            PatchMatchConfig(iterations=1),
        ),
    )
    api_case("API", "`top_k_views` with k = -3", lambda: top_k_views(torch.rand(5), 0, -3))
    api_case(
        "API",
        "`top_k_views` with an infinite score",
        lambda: top_k_views(torch.tensor([1.0, float("inf"), 2.0]), 0, 2),
    )
    api_case("API", "`fit_plane_ransac(threshold=0)`", lambda: fit_plane_ransac(torch.rand(20, 3), 0.0))
    api_case("API", "`normals_to_quats` of a (4,) tensor", lambda: normals_to_quats(torch.rand(4)))
    api_case("API", "`voxelize` with voxel_size 1e-40", lambda: voxelize(torch.rand(5, 3) * 100, 1e-40))
    api_case("API", "`load_scene(sample, scale=3000)`", lambda: load_scene(sample_scene_path(), scale=3000))


def main() -> None:
    """Run the groups and print the table."""
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--only", default="", help="run the groups whose name contains this")
    groups = {
        "scene": scene_cases,
        "colmap": colmap_cases,
        "flags": flag_cases,
        "viewer": viewer_cases,
        "api": api_cases,
    }
    only = parser.parse_args().only
    print("| # | area | case | outcome | s | message (first line; T = the trial's temporary folder) |")
    print("| --- | --- | --- | --- | --- | --- |", flush=True)
    try:
        for name, fn in groups.items():
            if only in name:
                fn()
    finally:
        shutil.rmtree(WORK, ignore_errors=True)


if __name__ == "__main__":
    main()
