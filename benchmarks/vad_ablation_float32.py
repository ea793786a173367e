"""``vad_ablation.py`` with the training images kept in float32 (as before issue 40), for A/B runs.

The trainer keeps its views' images as uint8 (``vadgs.train.objective``, docs/train.md); this
wrapper replaces the two conversions by identities, so a run's numerics are those of float32
images. Same arguments as ``vad_ablation.py``::

    python benchmarks/vad_ablation_float32.py ../shared/data/street_a \
        --config benchmarks/street_config_seed1.json --out runs/r20/street_a_vad_seed1_f32 --variants vadgs
"""

from __future__ import annotations

import runpy
import sys
from pathlib import Path

import vadgs.train.objective as objective

objective.to_uint8 = lambda x: x.detach().clone()
objective.from_uint8 = lambda x, device=None: x.to(device)

if __name__ == "__main__":
    sys.argv[0] = str(Path(__file__).with_name("vad_ablation.py"))
    runpy.run_path(sys.argv[0], run_name="__main__")
