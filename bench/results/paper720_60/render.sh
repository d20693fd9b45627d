#!/bin/bash
# The paper's protocol: the 720p renders at 60 frames (resumable; every render in the content-addressed cache).
# Code: a snapshot of stereorepro at commit d798c7b in /work/main/runs/720/code, made with
#   git archive d798c7b stereorepro | tar -x -C runs/720/code   (+ the built stereorepro/_core*.so copied in)
# and run by run_code.py (this folder's copy) from /work/main/runs/720; started 2026-12-03 08:58 UTC with
#   nohup ./run_all.sh > run_all.log 2>&1 &   (renice 15). Resumable: rerun it, cached renders are skipped.
# Renders keyed by renderer version ec0d6c5a840c27ce; analysis with the code of main: analyse.sh.
cd /work/main/runs/720
export STEREOREPRO_SHARED_SCENES=/work/shared/scenes
PY="/work/main/.venv/bin/python run_code.py"
COMMON="--resolution 1280x720 --frames 60 --ladder-spp 32 --reference-spp 32 --reference-chunk-spp 16 --no-flip --no-ssim --cache-dir /work/main/runs/720/cache --no-progress"
main() { [ -f first/$1/results.json ] || $PY experiment --scene $1 $COMMON --out first/$1; }
main shared_living_room
main shared_classroom
main shared_sponza
echo ALL DONE
