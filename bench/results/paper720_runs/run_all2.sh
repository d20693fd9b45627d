#!/bin/bash
# The 720p reproduction (issue #15): resumable, every render in the shared content-addressed cache.
# Code: a snapshot of stereorepro at commit aafc7cd (in /work/runs720/code); renders keyed by renderer version
# 9e51c24cf7b5e039 (= the renderer of 7b064f5; the tracer's later changes leave default renders bit-identical).
export STEREOREPRO_SHARED_SCENES=/work/shared/scenes
PY="/work/main/.venv/bin/python /work/runs720/run_code.py"
COMMON="--resolution 1280x720 --ladder-spp 32 --no-flip --cache-dir /work/runs720/cache --no-progress --renderer-version 9e51c24cf7b5e039"
main() { [ -f /work/runs720/$1/results.json ] || $PY experiment --scene $1 --frames 30 --reference-spp 32 --reference-chunk-spp 16 $COMMON --out /work/runs720/$1; }
study() { [ -f /work/runs720/study_$1/results.json ] || $PY experiment --scene $1 --frames 3 --reference-spp 256 --reference-chunk-spp 16 $COMMON --out /work/runs720/study_$1; }
jitter() { [ -f /work/runs720/jitter_$1/results.json ] || $PY experiment --scene $1 --frames 30 --reference-spp 32 --reference-chunk-spp 16 --jitter $COMMON --out /work/runs720/jitter_$1; }
main shared_living_room
jitter shared_living_room
study shared_living_room
main shared_classroom
main shared_sponza
study shared_classroom
study shared_sponza
echo ALL DONE
