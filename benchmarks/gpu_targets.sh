#!/usr/bin/env bash
# Issue 20's GPU figures in one run, on a machine with an NVIDIA GPU and CUDA (about 5 minutes):
#   1. the solver at 115k and 1 M particles, 100 steps each (target: 1 M at >= 100 steps/s, i.e. <= 10 ms a step);
#   2. capacity: 10 M particles, 10 steps, with the bytes per particle;
#   3. the live GGUI view of a ~200k dam break, one solver step per redraw, headless (target: >= 30 frames/s).
# A windowed figure needs a display; run bench_view.py there by hand with the same arguments.
#
#   bash benchmarks/gpu_targets.sh            # from the repository root, after `make install`
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PY:-.venv/bin/python}
export PYTHONPATH="$PWD/src${PYTHONPATH:+:$PYTHONPATH}"
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader || { echo "no NVIDIA GPU here" >&2; exit 1; }
echo "== solver, CUDA, 115k and 1 M, 100 steps"
"$PY" benchmarks/bench_solver.py --arch cuda --sizes 115000,1000000 --steps 100
echo "== capacity, CUDA, 10 M, 10 steps"
"$PY" benchmarks/bench_solver.py --arch cuda --sizes 10000000 --steps 10
echo "== live view, CUDA, ~200k particles, one step per redraw, 1280x720 headless"
"$PY" benchmarks/bench_view.py --arch cuda --n 200000 --live 200000 --steps-per-draw 1 --size 1280 720
