"""Stream compaction on the device: a deterministic exclusive prefix sum of integers.

Shared by the foam stage (diffuse/generator.py: survivors and new particles compacted in a fixed
order) and the sinks (sim/emitters.py: the particles left close up in order)."""

import taichi as ti

from . import runtime
from .grid import I1
from .launch import TEMPLATE

#: The exclusive prefix sum runs in at most SCAN_BLOCKS blocks of at least SCAN_MIN_BLOCK elements each (on
#: the CPU): a block is summed and scanned by one thread. 4096 blocks keep every core of a CPU busy.
SCAN_BLOCKS = 4096
SCAN_MIN_BLOCK = 256
#: On a GPU, at most SCAN_BLOCKS_GPU blocks of at least SCAN_MIN_BLOCK_GPU elements: a GPU runs a hundred thousand
#: threads at once, and each of its threads is slow to walk a long block (a load at a time, each waiting on
#: memory); 4096 threads of 660 elements each were about 2 % of an H100's threads for a 2.7 M-particle frame.
SCAN_BLOCKS_GPU = 1 << 17
SCAN_MIN_BLOCK_GPU = 16
#: The block sums are scanned in groups of SCAN_GROUP, one thread a group, then the groups' totals by one thread:
#: a single thread walking 131,072 block sums one load after another would take longer than the rest.
SCAN_GROUP = 512
#: Integers the caller's ``sums`` array holds: the block sums, the total, the groups' totals.
SCAN_SUMS = SCAN_BLOCKS_GPU + 1 + -(-SCAN_BLOCKS_GPU // SCAN_GROUP)


def scan_block(n: int, gpu: bool | None = None) -> int:
    """Elements per block of :func:`prefix_sum` for ``n`` elements (``gpu``: the layout for a GPU; by default,
    as the run's arch). The sum is the same whatever the layout: only the work's split changes."""
    if gpu is None:
        gpu = runtime.on_gpu()
    blocks, least = (SCAN_BLOCKS_GPU, SCAN_MIN_BLOCK_GPU) if gpu else (SCAN_BLOCKS, SCAN_MIN_BLOCK)
    return max(least, -(-int(n) // blocks))


@ti.kernel
def prefix_sum(n: ti.i32, block: ti.i32, a: I1, sums: I1, out: I1, grouped: TEMPLATE) -> ti.i32:
    """The exclusive prefix sum of a[0..n) (non-negative integers: counts or keep flags): out[j] = Σ_{k<j} a[k];
    returns Σ a. Passes, each a top-level loop (Taichi runs one after the other):
    (1) sums[b] = Σ a over block b (``block`` elements each, see scan_block), one block per thread;
    (2) the block sums scanned: by one thread, Σ a into sums[nb]; or, ``grouped`` (a GPU's many blocks), within
    groups of SCAN_GROUP, one group per thread, each group's total kept after the blocks' (sums[nb + 1 + g]),
    then (3) the groups' totals by one thread;
    (4) each block by its own thread from its offset (its block's, plus its group's where grouped).
    Integer sums in a fixed order: the same whatever the thread count or layout. One kernel, not one per pass:
    a launch costs about 0.1 ms of Python on the host, and the foam stage scans four times a frame. (Grouping on
    the CPU, with at most 4096 blocks, only adds a pass: 60 us a scan of 20k on 2 cores.)"""
    nb = (n + block - 1) // block
    for b in range(nb):
        s = 0
        for j in range(b * block, ti.min(n, (b + 1) * block)):
            s += a[j]
        sums[b] = s
    group = SCAN_GROUP if ti.static(grouped) else nb
    ng = (nb + group - 1) // group
    for g in range(ng):
        t = 0
        for b in range(g * group, ti.min(nb, (g + 1) * group)):
            c = sums[b]
            sums[b] = t
            t += c
        sums[nb + ti.static(1 if grouped else 0) + g] = t  # ungrouped: one group, Σ a
    if ti.static(grouped):
        for _ in range(1):
            t = 0
            for g in range(ng):
                c = sums[nb + 1 + g]
                sums[nb + 1 + g] = t
                t += c
            sums[nb] = t
    for b in range(nb):
        s = sums[b]
        if ti.static(grouped):
            s += sums[nb + 1 + b // SCAN_GROUP]
        for j in range(b * block, ti.min(n, (b + 1) * block)):
            c = a[j]
            out[j] = s
            s += c
    return sums[nb]


def exclusive_scan(n: int, a, sums, out, gpu: bool | None = None) -> int:
    """out[0..n) = the exclusive prefix sum of the integers a[0..n) (:func:`prefix_sum`); returns Σ a. ``sums``
    holds at least SCAN_SUMS integers (made once by the caller). ``gpu``: as :func:`scan_block`."""
    if n <= 0:
        return 0
    if gpu is None:
        gpu = runtime.on_gpu()
    return int(prefix_sum(n, scan_block(n, gpu), a, sums, out, gpu))
