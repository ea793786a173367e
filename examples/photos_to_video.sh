#!/usr/bin/env bash
# From a folder of photos to a trained VAD-GS model, its metrics, a video and a viewer file:
#
#   photos --vadgs sfm--> COLMAP project --vadgs train --vad--> run --vadgs eval--> eval.json
#                                           run --vadgs render --video--> video.mp4
#                                           run --vadgs export--> world_frame000.ply (any 3DGS viewer)
#
# Usage:  examples/photos_to_video.sh PHOTOS OUT [more vadgs train flags ...]
#   e.g.  examples/photos_to_video.sh ~/photos/castle runs/castle
#         ITERATIONS=1000 SCALE=0.125 examples/photos_to_video.sh ~/photos/castle runs/castle \
#             --vad.every-cycles 25
#
# Writes OUT/project (images/ = the photos, rotated ones upright, sparse/0, database.db, sfm.json) and
# OUT/run (checkpoint.pt, metrics.json, eval.json, video.mp4, export/frame000/world_frame000.ply).
#
# Settings, as environment variables:
#   ITERATIONS=3000   training steps
#   SCALE=            training resolution factor of the photos (default: vadgs train's)
#   THREADS=0         CPU threads of every step (0: all cores)
#   OVERWRITE=0       1: replace an earlier OUT/project and OUT/run (else the steps refuse)
#   NO_PROGRESS=0     1: no progress bars (logs, CI)
#   VADGS=vadgs       the command (e.g. "python -m vadgs.cli" in a source checkout)
set -euo pipefail

if [ $# -lt 2 ]; then
    echo "usage: $0 PHOTOS OUT [vadgs train flags ...]" >&2
    exit 2
fi
photos=$1
out=$2
shift 2

read -r -a vadgs <<< "${VADGS:-vadgs}"
threads=(--threads "${THREADS:-0}")
overwrite=()
if [ "${OVERWRITE:-0}" = 1 ]; then overwrite=(--overwrite); fi
progress=()
if [ "${NO_PROGRESS:-0}" = 1 ]; then progress=(--no-progress); fi
scale=()
if [ -n "${SCALE:-}" ]; then scale=(--scale "$SCALE"); fi

# what to expect, before anything runs: the photos found and the times measured on two machines
count=$(find "$photos" -type f \( -iname '*.jpg' -o -iname '*.jpeg' -o -iname '*.png' -o -iname '*.tif' \
    -o -iname '*.tiff' -o -iname '*.bmp' \) 2>/dev/null | wc -l | tr -d ' ')
echo "$count photos in $photos; ${ITERATIONS:-3000} training steps. Times measured (README), for scale:"
echo "  11 photos of 6 MP, idle 2-core CPU, 1000 steps at 368x272: SfM 44 s, training 6.5 min, the rest 30 s"
echo "  23 photos of 12 MP, busy 2-core CPU, 300 steps (working resolution): SfM 19 min, training 19-25 min, video 8 min"
echo "  (SfM grows with the photos' number and size; training with the steps and the pixels per step)"

start=$SECONDS
last=$SECONDS
step() {
    if [ "$last" != "$start" ] || [ "$1" != 1 ]; then echo "   ($((SECONDS - last)) s)"; fi
    last=$SECONDS
    echo
    echo "== step $1/5: $2"
}

step 1 "structure from motion: $photos -> $out/project"
"${vadgs[@]}" sfm "$photos" --out "$out/project" "${threads[@]}" "${overwrite[@]}" "${progress[@]}"

step 2 "training with VAD-GS -> $out/run"
"${vadgs[@]}" train "$out/project" --out "$out/run" --vad --iterations "${ITERATIONS:-3000}" \
    "${scale[@]}" "${threads[@]}" "${overwrite[@]}" "${progress[@]}" "$@"

step 3 "evaluation on the held-out photos -> $out/run/eval.json"
"${vadgs[@]}" eval "$out/run" "${threads[@]}" "${progress[@]}"

step 4 "video along a path through the photos' cameras -> $out/run/video.mp4"
"${vadgs[@]}" render "$out/run" --video "$out/run/video.mp4" "${threads[@]}" "${progress[@]}"

step 5 "export for 3DGS viewers -> $out/run/export"
"${vadgs[@]}" export "$out/run" "${threads[@]}"

echo "   ($((SECONDS - last)) s)"
echo
echo "done in $((SECONDS - start)) s: $out/run/eval.json, $out/run/video.mp4, $out/run/export"
