#!/bin/bash
# The Living Room at 1280x720, 60 frames, with the ladder extended to 64 spp (and so 64-spp references: the CLI asks
# --reference-spp >= --ladder-spp), for the one scheme whose error falls below the 32-spp rung
# (stereo_temporal_blend_alpha0.1, 42 of 60 frames): measured instead of extrapolated. Same snapshot as
# run_519eb67.sh (commit 519eb67), same render cache: the G-buffers and the first two 16-spp reference chunks are
# cache hits from run_519eb67.sh's Living Room run; the ladder and two more reference chunks are new
# (about 96 spp per eye-frame, about 2 h on 2 cores). FLIP and SSIM off (run_519eb67.sh has them).
# usage: bench/results/paper720_60/ladder64_519eb67.sh     (from /work/main; resumable: renders are cached)
set -e
cd /work/main
SNAP=runs/snap_519eb67
[ -d $SNAP/code/stereorepro ] || { echo "make $SNAP first: bench/results/paper360_60/run.sh's snapshot block" >&2; exit 2; }
export STEREOREPRO_SHARED_SCENES=/work/shared/scenes
[ -f runs/720/ladder64/shared_living_room/results.json ] || \
  .venv/bin/python $SNAP/run_code.py experiment --scene shared_living_room --resolution 1280x720 --frames 60 \
    --reference-spp 64 --reference-chunk-spp 16 --ladder-spp 64 --no-flip --no-ssim --no-progress \
    --cache-dir runs/720/cache --out runs/720/ladder64/shared_living_room > runs/lr720ladder64.log 2>&1
date; echo DONE
