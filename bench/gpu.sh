#!/usr/bin/env bash
# The prepared GPU check: the CUDA tests, then the reprojection ops' speed on the GPU (torch eager and,
# when onnxruntime-gpu is installed, onnxruntime's CUDAExecutionProvider) against the device's copy floor, at
# 1280x720, 1920x1080 and 3840x2160 -> bench/results/gpu.{json,md}. At most 5 minutes; installs nothing.
#
#   bash bench/gpu.sh                  # from the repository root, with the project's .venv (or PYTHON=...)
#   bash bench/gpu.sh --sizes 720p     # options go to bench/gpu.py (--help)
#
# Without a CUDA device it prints why and exits 0 without writing anything. Exit 1: the CUDA tests failed.
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."
PY="${PYTHON:-}"
if [ -z "$PY" ]; then
  if [ -x .venv/bin/python ]; then PY=.venv/bin/python; else PY=python3; fi
fi
# gpu.py keeps to a 270 s budget (skipping sizes that would not fit); the hard limit is a safety net.
status=0
timeout --kill-after=10 300 "$PY" bench/gpu.py "$@" || status=$?
if [ "$status" -eq 124 ] || [ "$status" -eq 137 ]; then
  echo "bench/gpu.sh: stopped at the 5-minute limit (results not written)" >&2
fi
exit "$status"
