#!/bin/bash
# The 60-frame Living Room with every option variant, FLIP and SSIM off (to fit a session), from the cache only.
cd /work/main
export STEREOREPRO_SHARED_SCENES=/work/shared/scenes
.venv/bin/python -m stereorepro experiment --scene shared_living_room --resolution 1280x720 --frames 60 --ladder-spp 32 \
    --reference-spp 32 --reference-chunk-spp 16 --option-variants --no-flip --no-ssim --no-progress \
    --cache-dir /work/main/runs/720/cache --renderer-version ec0d6c5a840c27ce --out runs/720/quick/shared_living_room
