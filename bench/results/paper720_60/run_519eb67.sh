#!/bin/bash
# Session 2026-12-03 (night): the 720p cells the earlier runs left empty, from a snapshot of commit 519eb67 (made as
# bench/results/paper360_60/run.sh makes it; its render sources are d798c7b's, so the renders equal the earlier
# runs' bit for bit, though its cache key differs). The render cache starts empty, so each run renders everything.
#   shared_classroom: the full protocol with every option, FLIP and SSIM on every 4th frame.
#   flip_shared_living_room (out: runs/720/flip/shared_living_room): the Living Room's FLIP and SSIM only. FLIP and
#     SSIM compare the schemes' outputs with the 32-spp reference and do not use the ladder, so the ladder stops at
#     2 spp (half the render time); this run's effective spp are not used (the Living Room's come from
#     analyse_quick.sh).
# usage: bench/results/paper720_60/run_519eb67.sh     (from /work/main; resumable: renders are cached)
# Measured: Classroom wall 6315 s, Living Room (niced, beside it) 8177 s, 2 cores; the runs' files are copied into
# bench/results/paper720_60/{shared_classroom,flip_shared_living_room}/ and tabled by bench/paper_tables.py.
set -e
cd /work/main
SNAP=runs/snap_519eb67
[ -d $SNAP/code/stereorepro ] || { echo "make $SNAP first: bench/results/paper360_60/run.sh's snapshot block" >&2; exit 2; }
export STEREOREPRO_SHARED_SCENES=/work/shared/scenes
SR=".venv/bin/python $SNAP/run_code.py experiment --resolution 1280x720 --frames 60 --reference-spp 32 --reference-chunk-spp 16 --perceptual-every 4 --no-progress --cache-dir runs/720/cache"
[ -f runs/720/final/shared_classroom/results.json ] || \
  $SR --scene shared_classroom --ladder-spp 32 --option-variants --out runs/720/final/shared_classroom > runs/cr720.log 2>&1 &
[ -f runs/720/flip/shared_living_room/results.json ] || \
  nice -n 19 $SR --scene shared_living_room --ladder-spp 2 --out runs/720/flip/shared_living_room > runs/lr720flip.log 2>&1 &
wait
date; echo DONE
