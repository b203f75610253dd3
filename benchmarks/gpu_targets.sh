#!/usr/bin/env bash
# Issue 20's and issue 31's GPU figures in one run, on a machine with an NVIDIA GPU and CUDA
# (each step has its own time limit, so the whole run stays under about 8 minutes on an H100):
#   1. the solver at 1 M (target >= 100 steps/s), 10 M and 50 M particles, with bytes per particle
#      (the neighbour grid's memory is set by the particles: dense cell table in the benchmark's tank,
#      5 cells a particle, hashed where the domain is much larger); list building with the dense and the
#      hashed cell table at 1 M and 10 M, and in a domain 1000x the fluid's volume, and the dense table
#      with its cell counts' block sums walked by one thread, as before 2026-11-28 (dense*; bench_grid.py);
#   2. `simulate --profile` of the H = 2a dam break with foam on and off, at r = 2 mm and r = 0.8 mm
#      (the diffuse phase's share, target <= 20 %, and foam-on over foam-off, target >= 0.8); at r = 2 mm twice,
#      with the read-back pageable once more each time, and once more each with Taichi's kernel profiler (each
#      kernel's device time a frame: what foam adds on the device against what it adds to the loop);
#   3. frames, run.json and checkpoints written by the background writer against in the loop;
#      resident host memory and GPU memory in use over 60 frames with foam on and off (bench_memory.py);
#   4. `whitecap foam --arch cuda` post-processing of a 1 M-particle sequence (target >= 30 frames/s; on a RAM disk
#      once more with each kernel's device time against the frames' wall time), and its
#      files alone through the background writer, one after the other, side by side, with the next frame's beside
#      them (as whitecap writes them since 2026-11-28's fifteenth session), with four frames' beside each other (lanes
#      twice as deep: whether more threads a lane write more a second on a machine of many cores), and their bytes
#      packed beforehand (what packing the records on the host costs; bench_writer.py), on the machine's disk and on
#      a RAM disk,
#      and the foam stage's prefix sum in the CPU's layout against the GPU's (bench_scan.py);
#   5. the live GGUI view of a ~200k dam break, one solver step per redraw, headless (target >= 30 frames/s);
#   6. an experiment: the diffuse particles' advection with the particles sorted by cell (bench_advect_order.py).
# A windowed figure needs a display; run bench_view.py there by hand with the same arguments.
#
# Steps run the targets the last lease left unmet first (foam on over off at 1 M, `whitecap foam` at 1 M); with
# BUDGET=SECONDS the whole run stops there: a step is given at most what is left (and skipped with under 20 s),
# so a lease shorter than 8 minutes still brings back the first figures.
#
#   bash benchmarks/gpu_targets.sh            # from the repository root, after `make install`
#   BUDGET=480 bash benchmarks/gpu_targets.sh # at most 8 minutes in all
# On a GPU machine that reaches no package registry (Python 3.12 there): build .whl and .gl with
# benchmarks/gpu_bundle.sh where pip reaches one, carry them over, then
#   source benchmarks/gpu_env.sh && BUDGET=480 bash benchmarks/gpu_targets.sh
# Before a lease, on any machine: DRY=1 runs every step on the CPU at a few thousand particles (about a minute on 2
# cores; its figures mean nothing), so that a step broken since the last lease shows here ("!! ... stopped"), not
# on the GPU's clock.
set -uo pipefail
cd "$(dirname "$0")/.."
PY=${PY:-.venv/bin/python}
export PYTHONPATH="$PWD/src${PYTHONPATH:+:$PYTHONPATH}"
DRY=${DRY:-0}
if [[ $DRY == 1 ]]; then
    ARCH=cpu
    echo "DRY=1: every step on the CPU at small sizes, to check that it runs (the figures mean nothing)"
else
    ARCH=cuda
    nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader || { echo "no NVIDIA GPU here" >&2; exit 1; }
fi
n() { if [[ $DRY == 1 ]]; then echo "$2"; else echo "$1"; fi; }  # n REAL DRY: a step's size, the lease's or the dry run's

END=$(( $(date +%s) + ${BUDGET:-100000} ))
STOPPED=0
step() {  # step SECONDS TITLE COMMAND...: run with a time limit; a failure is reported and the script goes on
    local limit=$1 title=$2 left=$(( END - $(date +%s) ))
    shift 2
    if (( left < 20 )); then echo "== $title: skipped (BUDGET spent)"; return; fi
    (( limit > left )) && limit=$left
    echo "== $title"
    local t0=$SECONDS
    timeout "$limit" "$@" || { echo "!! $title: stopped (exit $?)"; STOPPED=$(( STOPPED + 1 )); }
    echo "   ($(( SECONDS - t0 )) s)"
}

step 90  "solver, CUDA, 1 M, 100 steps"        "$PY" benchmarks/bench_solver.py --arch $ARCH --sizes "$(n 1000000 20000)" --steps "$(n 100 3)"
# foam post-processing, and the same with its frames read back array by array and packed by the writer (as before
# 2026-11-28's records made on the device), alternating
step 90  "foam post-processing, CUDA, 1 M particles, 10 frames (and read back array by array)" \
    "$PY" benchmarks/bench_foam.py --arch $ARCH --particles "$(n 1000000 20000)" --frames "$(n 10 5)" --profile --arrays
# foam on against off (target >= 0.8x), twice, each time with foam on once more with the read-back's host arrays
# pageable (pinned by default since the H200 lease of 2026-11-28: 133 ms a frame against 155 pageable, measured once);
# then foam on and off once more each with Taichi's kernel profiler: each kernel's device time a frame, where
# foam-on's extra time goes on the device (the host's timers hold the device's waits wherever a value is read back)
step 230 "simulate with foam on and off, CUDA, r = 2 mm, 40 frames, twice (and foam on: pageable read-back; kernels)" \
    "$PY" benchmarks/bench_simulate_foam.py --arch $ARCH --radius "$(n 0.002 0.012)" --frames "$(n 40 3)" --pin \
    --repeat 2 --kernels
# what the foam pass's files cost the writer: one after the other on its thread, or fluid and diffuse side by side
step 60  "a frame's files through the writer, 1 M fluid + 1.6 M diffuse: one thread, lanes, frames side by side, deeper lanes, bytes packed beforehand" \
    "$PY" benchmarks/bench_writer.py --fluid "$(n 1000000 20000)" --diffuse "$(n 1600000 30000)" --frames "$(n 10 3)" --pairs "$(n 3 1)"
step 30  "the foam stage's prefix sum on CUDA, its CPU layout against its GPU layout" \
    "$PY" benchmarks/bench_scan.py --arch $ARCH --sizes "$(n 1000000,2700000,33554432 10000)" --repeats "$(n 50 3)"
# the foam pass with the sequence and the files written on a RAM disk: what the machine's disk takes of the rate;
# then one more pass with Taichi's kernel profiler: the frames' device time against their wall time (the loop's
# own work beyond the device's: at 1 M on the H200, 85 ms a frame, most of it unnamed by the host's timers)
[ -d /dev/shm ] && step 75 "foam post-processing, CUDA, 1 M particles, 10 frames, on a RAM disk (and kernels)" \
    env TMPDIR=/dev/shm "$PY" benchmarks/bench_foam.py --arch $ARCH --particles "$(n 1000000 20000)" --frames "$(n 10 5)" \
    --profile --kernels
[ -d /dev/shm ] && step 40 "a frame's files through the writer on a RAM disk: one thread, lanes, frames side by side, deeper lanes, bytes" \
    "$PY" benchmarks/bench_writer.py --dir /dev/shm --fluid "$(n 1000000 20000)" --diffuse "$(n 1600000 30000)" --frames "$(n 10 3)" --pairs "$(n 3 1)"
step 180 "solver, CUDA, 10 M and 50 M, 10 steps" "$PY" benchmarks/bench_solver.py --arch $ARCH --sizes "$(n 10000000,50000000 20000,40000)" --steps "$(n 10 2)"
step 150 "simulate with foam on and off, CUDA, r = 0.8 mm, 4 frames" \
    "$PY" benchmarks/bench_simulate_foam.py --arch $ARCH --radius "$(n 0.0008 0.012)" --frames "$(n 4 2)"
step 120 "memory over 60 frames with foam on and off, CUDA, r = 2 mm (flat once the budget is reached)" \
    "$PY" benchmarks/bench_memory.py --arch $ARCH --radius "$(n 0.002 0.012)" --frames "$(n 60 4)"
step 60  "live view, CUDA, ~200k particles, one step per redraw, 1280x720 headless" \
    "$PY" benchmarks/bench_view.py --arch $ARCH --n "$(n 200000 5000)" --live "$(n 200000 5000)" --steps-per-draw 1 --size 1280 720
step 90  "neighbour grid, CUDA, dense vs hashed cell table, 1 M and 10 M" \
    "$PY" benchmarks/bench_grid.py --arch $ARCH --sizes "$(n 1000000,10000000 20000)" --repeats "$(n 5 1)"
step 60  "background writer against in the loop, CUDA, r = 2 mm" \
    "$PY" benchmarks/bench_output.py --arch $ARCH --radius "$(n 0.002 0.012)" --frames "$(n 20 3)"
# an experiment, last (skipped first when the budget runs out): the diffuse particles' advection in the fluid grid's
# cell order against their stored, nearly random one (on 2 CPU cores the same time; a GPU's warps may differ)
step 60  "experiment: advect_diffuse on the live diffuse particles as stored and sorted by cell, CUDA, 1 M" \
    "$PY" benchmarks/bench_advect_order.py --arch $ARCH --particles "$(n 1000000 20000)" --frames "$(n 8 5)"
# the exit status says whether every step that ran finished (what DRY=1 is for)
echo "== $STOPPED step(s) stopped"
(( STOPPED == 0 ))
