#!/bin/bash
# The paper's protocol at 640x360 (60 frames, ladder 1..32, 32-spp references in two chunks, every history option,
# FLIP and SSIM on every 4th frame) for the scenes whose 1280x720 option runs could not be redone here: the render
# cache of the 720p runs does not outlive a session, and a 720p Classroom run from nothing takes about 2 h of this
# 2-core machine. Code: a snapshot of the commit below in runs/snap_<commit>, run by paper720_60/run_code.py's rule.
# usage: bench/results/paper360_60/run.sh SCENE...     (from /work/main; resumable per scene: renders are cached)
set -e
cd /work/main
COMMIT=519eb67
SNAP=runs/snap_$COMMIT
if [ ! -d $SNAP/code/stereorepro ]; then
  mkdir -p $SNAP/code
  git archive $COMMIT stereorepro | tar -x -C $SNAP/code
  cp .venv/lib/python3.11/site-packages/stereorepro/_core*.so $SNAP/code/stereorepro/
  sed 's/(commit d798c7b)/(see run.sh)/' bench/results/paper720_60/run_code.py > $SNAP/run_code.py
fi
export STEREOREPRO_SHARED_SCENES=/work/shared/scenes
A="--resolution 640x360 --frames 60 --ladder-spp 32 --reference-spp 32 --reference-chunk-spp 16 --option-variants --perceptual-every 4 --no-progress --cache-dir runs/360/cache"
for s in "$@"; do
  [ -f runs/360/final/$s/results.json ] || { date; .venv/bin/python $SNAP/run_code.py experiment --scene $s $A --out runs/360/final/$s; }
done
date; echo QUEUE DONE "$@"
