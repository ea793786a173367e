#!/usr/bin/env bash
# Download (here, with network) the wheels the GPU machine lacks into .whl/ at the repo root, for
# benchmarks/gpu_check.sh to install there (it has no network). Python 3.12, x86_64 manylinux.
#
#   bash benchmarks/gpu_wheels.sh      # then: run(command='bash benchmarks/gpu_check.sh "$OUT"', carry=[".whl"])
#
# Also writes .whl/data (gsplat's examples, the COLMAP sample as text) for the simple_trainer section:
# run it with the development venv's python (PYTHON=...; it needs vadgs and pycolmap).
#
# Versions: those of the development venv (pip show). The device has torch, numpy, scipy,
# scikit-image, networkx, pillow, matplotlib, tqdm, ... but not these. Left out: pycolmap (large;
# imported lazily, only by COLMAP input/export: vadgs, vadgs.train, the renderer, the strategy and
# the check import without it; its tests skip), rtree (benchmarks only). .whl/ is git-ignored (.gitignore;
# else .git/info/exclude gets it), so it travels only as a carried path.
set -euo pipefail
cd "$(dirname "$0")/.."
WHEELS=(
    # vadgs's own dependencies
    kornia==0.9.0 kornia_rs==0.2.0 plyfile==1.1.5 trimesh==5.2.0
    tyro==1.0.17 docstring_parser==0.18.0 typeguard==4.6.1
    embreex==4.4.0.post1  # make_segment's ray caster (segment_memory)
    # gsplat (its CUDA code compiles on first use: ninja) and what it imports
    gsplat==1.5.3 ninja==1.13.2 jaxtyping==0.3.11 wadler_lindig==0.1.8
    rich==14.3.4 markdown-it-py==4.3.0 mdurl==0.1.2 Pygments==2.21.0
)
mkdir -p .whl
git check-ignore -q .whl || echo '/.whl/' >> "$(git rev-parse --git-path info/exclude)"
for w in "${WHEELS[@]}"; do
    python3 -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
        --platform manylinux_2_28_x86_64 --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64 \
        --platform manylinux_2_5_x86_64 --platform manylinux1_x86_64 -d .whl "$w"
done
# the simple_trainer section's inputs (no network nor pycolmap there): gsplat's examples from
# ../shared and the COLMAP sample as a text model (tests/data/colmap_sample.py, with pycolmap here)
if [ -e .whl/data ] && [ ! -e .whl/data/.gpu_wheels ]; then  # never remove a folder this script did not write
    echo "gpu_wheels.sh: .whl/data exists and was not written by this script: move it away first" >&2
    exit 1
fi
rm -rf .whl/data && mkdir -p .whl/data && touch .whl/data/.gpu_wheels
if [ -d ../shared/third_party/gsplat-v1.5.3 ]; then
    cp -r ../shared/third_party/gsplat-v1.5.3 .whl/data/
else
    echo "gpu_wheels.sh: no ../shared/third_party/gsplat-v1.5.3: the simple_trainer section will be skipped"
fi
"${PYTHON:-python3}" -c "import sys; sys.path.insert(0, '.')
from pathlib import Path
from tests.data.colmap_sample import write_sample_colmap
write_sample_colmap(Path('.whl/data/colmap_sample'), n_points=1500, link_images=False, text=True)"
ls -l .whl
echo "wheels: $(ls .whl/*.whl | wc -l), total $(du -cb .whl/*.whl | tail -1 | awk '{printf "%.1f MiB", $1 / 2^20}');" \
    "data $(du -sb .whl/data | awk '{printf "%.1f MiB", $1 / 2^20}')"
