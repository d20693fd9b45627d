#!/bin/bash
# The 60-frame 1280x720 tables: analysis of the renders that render.sh cached (every entry a cache hit), with the
# code of /work/main, FLIP and SSIM on, and Table 2's option variants. Renderer version ec0d6c5a840c27ce = the
# renders of render.sh (snapshot of commit d798c7b).
# usage: analyse.sh SCENE     (shared_living_room | shared_classroom | shared_sponza)
set -e
cd /work/main
export STEREOREPRO_SHARED_SCENES=/work/shared/scenes
.venv/bin/python -m stereorepro experiment --scene "$1" --resolution 1280x720 --frames 60 --ladder-spp 32 \
    --reference-spp 32 --reference-chunk-spp 16 --option-variants --no-progress \
    --cache-dir /work/main/runs/720/cache --renderer-version ec0d6c5a840c27ce --out "runs/720/final/$1"
