#!/bin/bash
# Session 2026-12-03 (evening): code = the snapshot in runs/snap_16b1a2f (commit 16b1a2f), run by its run_code.py.
# Its renderer version is ec0d6c5a840c27ce (the render sources are d798c7b's), so the Sponza final run renders its
# cache misses itself (no separate first run). Every option variant, FLIP and SSIM on every 4th frame.
# usage: final.sh SCENE...   (one process per call; the Sponza one at normal priority, the others at nice 19)
cd /work/main
export STEREOREPRO_SHARED_SCENES=/work/shared/scenes
SR="/work/main/.venv/bin/python runs/snap_16b1a2f/run_code.py"
A="--resolution 1280x720 --frames 60 --ladder-spp 32 --reference-spp 32 --reference-chunk-spp 16 --option-variants --perceptual-every 4 --no-progress --cache-dir /work/main/runs/720/cache"
for s in "$@"; do
  [ -f runs/720/final/$s/results.json ] || { date; $SR experiment --scene $s $A --out runs/720/final/$s; }
done
date; echo QUEUE DONE "$@"
