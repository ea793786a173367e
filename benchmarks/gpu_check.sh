#!/usr/bin/env bash
# The GPU check on a CUDA machine without network: install the carried wheels (.whl/, from
# benchmarks/gpu_wheels.sh) that are missing there, print the machine, run benchmarks/gpu_check.py
# under a hard overall timeout. Writes $OUT/gpu_check.json (rewritten after every section) and
# $OUT/gpu_check.log.
#
#   bash benchmarks/gpu_check.sh "$OUT"          # docs/benchmarks.md, "The GPU check"
#   bash benchmarks/gpu_check.sh "$OUT" --only environment segment_memory   # a rerun of some sections
#
# GPU_CHECK_TIMEOUT (default 450 s) bounds the python run (its own budget is 20 s less), so that
# with the install and nvidia-smi the whole stays under the device call's 480 s.
set -uo pipefail
OUT=${1:-${OUT:-/tmp/gpu_check}}
shift || true  # the rest goes to gpu_check.py (--only SECTION ...)
mkdir -p "$OUT"
cd "$(dirname "$0")/.."
exec > >(tee "$OUT/gpu_check.log") 2>&1
TIMEOUT=${GPU_CHECK_TIMEOUT:-450}
SITE=/tmp/site
t0=$(date +%s)

if [ -d .whl ]; then
    # only the wheels whose distribution is not installed here (never shadow the machine's own)
    missing=()
    for whl in .whl/*.whl; do
        dist=$(basename "$whl" | cut -d- -f1)
        if ! python3 -c "import importlib.metadata as m, sys; m.version(sys.argv[1])" "$dist" 2>/dev/null; then
            missing+=("$whl")
        fi
    done
    echo "[gpu_check.sh] installing ${#missing[@]} wheels into $SITE: ${missing[*]##*/}"
    if [ ${#missing[@]} -gt 0 ]; then
        python3 -m pip install -q --no-index --no-deps --no-compile --target "$SITE" "${missing[@]}"
    fi
fi
export PYTHONPATH="$PWD:$SITE${PYTHONPATH:+:$PYTHONPATH}"
export PATH="$SITE/bin:$PATH"  # ninja, for gsplat's JIT compile
export TORCH_EXTENSIONS_DIR=${TORCH_EXTENSIONS_DIR:-/tmp/torch_extensions}
export OMP_NUM_THREADS=${OMP_NUM_THREADS:-8}
echo "[gpu_check.sh] setup took $(( $(date +%s) - t0 )) s"

nvidia-smi || echo "[gpu_check.sh] nvidia-smi failed"
command -v nvcc && nvcc --version | tail -2
python3 - <<'EOF'
import sys, torch
print("python", sys.version.split()[0], "torch", torch.__version__, "cuda", torch.version.cuda,
      "available", torch.cuda.is_available())
import vadgs
print("vadgs", vadgs.__file__)
EOF

timeout -k 10 "$TIMEOUT" python3 benchmarks/gpu_check.py --out "$OUT/gpu_check.json" --budget $(( TIMEOUT - 20 )) "$@"
rc=$?
echo "[gpu_check.sh] gpu_check.py exited $rc (124: the overall timeout) after $(( $(date +%s) - t0 )) s"
python3 - "$OUT/gpu_check.json" <<'EOF'
import json, sys
try:
    d = json.load(open(sys.argv[1]))
except Exception as e:
    sys.exit(f"no JSON: {e}")
for name, s in d["sections"].items():
    print(f"{name:16s} {s['status']:8s} {s.get('seconds', 0):7.1f} s  {s.get('reason', '')[:150]}")
EOF
exit $rc
