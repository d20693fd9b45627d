#!/bin/bash
# Re-analysis of the cached 720p renders with the code of /work/main (no rendering: every entry is a cache hit).
export STEREOREPRO_SHARED_SCENES=/work/shared/scenes
PY=/work/main/.venv/bin/python
COMMON="--resolution 1280x720 --ladder-spp 32 --no-flip --no-ssim --cache-dir /work/runs720/cache --no-progress --renderer-version 9e51c24cf7b5e039 --reference-spp 32 --reference-chunk-spp 16 --frames 30"
# usage: final.sh SCENE [jitter]
$PY -m stereorepro experiment --scene $1 $COMMON --out /work/runs720/final/$1
[ "$2" = jitter ] && $PY -m stereorepro experiment --scene $1 $COMMON --jitter --out /work/runs720/final/jitter_$1
