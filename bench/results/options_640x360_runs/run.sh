#!/bin/bash
# Option variants at 640x360 (issue #29), code of main at the commit below; renders cached in runs/opt360/cache.
cd /work/main
export STEREOREPRO_SHARED_SCENES=/work/shared/scenes
C="--resolution 640x360 --frames 16 --ladder-spp 32 --reference-spp 32 --reference-chunk-spp 16 --no-flip --no-ssim --option-variants --alphas 0.1 --no-progress --cache-dir runs/opt360/cache"
for s in shared_living_room living_room_moving_light atrium_moving_light; do  # atrium_moving_light: run at eb27f8e
  [ -f runs/opt360/$s/results.json ] || .venv/bin/python -m stereorepro experiment --scene $s $C --out runs/opt360/$s
done
echo ALL DONE
