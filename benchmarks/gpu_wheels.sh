#!/usr/bin/env bash
# Download (here, with network) the wheels the GPU machine lacks into .whl/ at the repo root, for
# benchmarks/gpu_check.sh to install there (it has no network). Python 3.12, x86_64 manylinux.
#
#   bash benchmarks/gpu_wheels.sh      # then: run(command='bash benchmarks/gpu_check.sh "$OUT"', carry=[".whl"])
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
ls -l .whl
echo "wheels: $(ls .whl/*.whl | wc -l), total $(du -cb .whl/*.whl | tail -1 | awk '{printf "%.1f MiB", $1 / 2^20}')"
