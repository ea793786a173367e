"""A screenshot of ``vadgs view`` for the docs: serve a run, load it in headless Chromium, write a PNG.

Usage: ``python tools/viewer_screenshot.py RUN OUT.png [--frame F] [--filter all|only|without]``.
"""

from __future__ import annotations

import argparse
import socket

import viser

from vadgs.train.run import frame_position, load_run
from vadgs.viewer import FILTERS, browser_screenshot, build_viewer


def main() -> None:
    """Parse the arguments, serve the run, take the screenshot."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run")
    ap.add_argument("out")
    ap.add_argument("--frame", type=int, help="frame index (default: the first)")
    ap.add_argument("--filter", choices=["all", "only", "without"], default="all")
    ap.add_argument("--size", default="1280x800")
    ap.add_argument("--budget-ms", type=int, default=60000)
    args = ap.parse_args()
    run = load_run(args.run)
    model, scene = run.model, run.scene
    _, position = frame_position(scene, args.frame, "--frame")
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    server = viser.ViserServer(host="127.0.0.1", port=port, verbose=False)
    try:
        viewer = build_viewer(model, scene, server, position)
        viewer.set_filter(FILTERS[["all", "only", "without"].index(args.filter)])
        w, h = (int(x) for x in args.size.split("x"))
        print(browser_screenshot(f"http://127.0.0.1:{port}", args.out, (w, h), args.budget_ms))
    finally:
        server.stop()


if __name__ == "__main__":
    main()
