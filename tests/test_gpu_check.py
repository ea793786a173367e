"""benchmarks/gpu_check.py in its CPU mode at the smallest sizes (``--cpu --tiny``): every section
recorded with a status, the CPU sections with numbers, the CUDA ones skipped with a reason.

``vadgs.data.synthetic.make_segment`` is replaced by a stand-in that copies the bundled sample, so
the segment section's code runs here whether or not the generator is on this branch (and fast).
"""

from __future__ import annotations

import importlib.util
import json
import shutil
import sys
import types
from pathlib import Path

import pytest
import torch

from vadgs.data import sample_scene_path

REPO = Path(__file__).resolve().parents[1]


def _gpu_check():
    spec = importlib.util.spec_from_file_location("_vadgs_gpu_check", REPO / "benchmarks" / "gpu_check.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@pytest.fixture
def stand_in_segment(monkeypatch):
    calls = []

    def make_segment(out, **sizes):
        calls.append(sizes)
        shutil.copytree(sample_scene_path(), out)

    synthetic = types.ModuleType("vadgs.data.synthetic")
    synthetic.make_segment = make_segment
    monkeypatch.setitem(sys.modules, "vadgs.data.synthetic", synthetic)
    return calls


@pytest.mark.skipif(torch.cuda.is_available(), reason="the CPU mode's expectations (no CUDA sections)")
def test_cpu_mode_writes_every_section(tmp_path, stand_in_segment):
    gc = _gpu_check()
    out = tmp_path / "gpu_check.json"
    threads = torch.get_num_threads()
    try:
        gc.main(["--cpu", "--tiny", "--out", str(out)])
    finally:
        torch.set_num_threads(threads)
    data = json.loads(out.read_text())
    sections = data["sections"]
    assert list(sections) == gc.SECTIONS and data["finished"] and data["device"] == "cpu"
    for name, s in sections.items():
        assert s["status"] in ("ok", "skipped"), (name, s.get("reason"), s.get("traceback"))
        assert s["seconds"] >= 0 and (s["status"] == "ok" or s["reason"]), name
    for name in ("gsplat_build", "gsplat_vs_torch", "cuda_tests"):
        assert sections[name] == {**sections[name], "status": "skipped", "reason": "no CUDA device"}
    # the pytest machinery ran on one file: its CUDA cases collected and skipped
    dry = sections["cuda_tests"]["dry_run"]
    assert dry["counts"]["skipped"] > 0 and dry["counts"]["failed"] == dry["counts"]["errors"] == 0
    assert sections["environment"]["torch"] == torch.__version__
    ops = sections["vad_ops"]["ops"]
    for op in ("zbuffer", "selection", "patchmatch", "reconstruct"):
        assert ops[op]["calls"] > 0 and ops[op]["in_event_median_ms"] > 0, op
    assert ops["zbuffer"]["replay_median_ms"] > 0 and ops["patchmatch"]["replay_median_ms"] > 0
    torch_row = sections["train_step"]["backends"]["torch"]
    assert torch_row["step_ms_median"] > 0
    if torch_row.get("event_ops_calls", {}).get("reconstruct"):  # the event's operations, timed
        ops_ms = torch_row["event_ops_median_ms"]
        calls = torch_row["event_ops_calls"]  # a pair's share of the event's batched reconstruction
        assert ops_ms["reconstruct"] * calls["reconstruct"] >= ops_ms["patchmatch"] * calls["patchmatch"] > 0
    seg = sections["segment_memory"]
    assert stand_in_segment == [{**gc.SIZES["tiny"]["seg"], "workers": 1, "progress": False}]
    assert seg["steps"] == gc.SIZES["tiny"]["seg_steps"] and seg["peak_host_rss_gib"] > 0
    assert "peak_gpu_gib" not in seg and seg["event_s"] > 0
    st = sections["simple_trainer"]
    from tests.train.gsplat_simple_trainer import GSPLAT_EXAMPLES

    if GSPLAT_EXAMPLES.is_dir():  # gsplat's own script with the diff, a bare machine's stand-ins
        vad = st["runs"]["vad"]
        assert vad["stand_ins"] == ["fused_ssim", "nerfview", "viser", "pycolmap"] and vad["rows_consistent"]
        assert vad["gaussians"] == vad["val"]["num_GS"] == 1500 and vad["val"]["psnr"] > 5
        assert vad["step_ms_median"] > 0 and st["data_factor"] == gc.SIZES["tiny"]["st_factor"]
    else:
        assert st["status"] == "skipped" and "no gsplat examples" in st["reason"]


def test_compare_renderers_on_the_cpu():
    """The comparison of ``gsplat_vs_torch`` with gsplat's pure-torch reference (CPU): agreement
    at float32 round-off, every gradient compared."""
    gc = _gpu_check()
    res = gc.compare_renderers(gc.SIZES["tiny"], "cpu", "torch")
    assert res["covered_fraction"] > 0.05 and res["torch_ms"] > 0 and res["gsplat_ms"] > 0
    assert set(res["gradients"]) == {"means", "quats", "scales", "opacities", "colors"}
    for name, e in {**res["images"], **res["gradients"]}.items():
        assert e["max_rel"] < 1e-3, (name, e)


def test_steady_step_time_of_a_record():
    """simple_trainer's step time: the second half of the run, the steps that held an event left out."""
    gc = _gpu_check()
    # 10 steps 20 ms apart but step 7, an event, took 500 ms; the first half (a slow start) is left out
    t, steps = 0.0, []
    for i in range(10):
        t += 0.5 if i in (1, 7) else 0.02
        steps.append([i, 100, t])
    assert gc._steady_step_ms(steps, [7]) == pytest.approx(20.0)
    assert gc._steady_step_ms(steps, []) == pytest.approx(20.0)  # the median: one slow step of four
    assert gc._steady_step_ms([[0, 100], [1, 100]], []) is None  # an old record without times
