"""Stream compaction on the device: a deterministic exclusive prefix sum of integers.

Shared by the foam stage (diffuse/generator.py: survivors and new particles compacted in a fixed
order) and the sinks (sim/emitters.py: the particles left close up in order)."""

import taichi as ti

from .grid import I1

#: The exclusive prefix sum runs in at most SCAN_BLOCKS blocks of at least SCAN_MIN_BLOCK elements
#: each: a block is summed and scanned by one thread, the block sums by one thread. 4096 blocks keep
#: every core of a CPU and thousands of GPU threads busy, and the serial scan of the sums short.
SCAN_BLOCKS = 4096
SCAN_MIN_BLOCK = 256


def scan_block(n: int) -> int:
    """Elements per block of :func:`prefix_sum` for ``n`` elements."""
    return max(SCAN_MIN_BLOCK, -(-int(n) // SCAN_BLOCKS))


@ti.kernel
def prefix_sum(n: ti.i32, block: ti.i32, a: I1, sums: I1, out: I1) -> ti.i32:
    """The exclusive prefix sum of a[0..n) (non-negative integers: counts or keep flags): out[j] = Σ_{k<j} a[k];
    returns Σ a. Three passes, each a top-level loop (Taichi runs one after the other): sums[b] = Σ a over block
    b (``block`` elements each, see scan_block), one block per thread; the block sums scanned by one thread;
    then each block by its own from its offset. Integer sums in a fixed order: the same whatever the thread
    count. One kernel, not one per pass: a launch costs about 0.1 ms of Python on the host, and the foam stage
    scans four times a frame."""
    nb = (n + block - 1) // block
    for b in range(nb):
        s = 0
        for j in range(b * block, ti.min(n, (b + 1) * block)):
            s += a[j]
        sums[b] = s
    for _ in range(1):
        t = 0
        for b in range(nb):
            c = sums[b]
            sums[b] = t
            t += c
        sums[nb] = t
    for b in range(nb):
        s = sums[b]
        for j in range(b * block, ti.min(n, (b + 1) * block)):
            c = a[j]
            out[j] = s
            s += c
    return sums[nb]


def exclusive_scan(n: int, a, sums, out) -> int:
    """out[0..n) = the exclusive prefix sum of the integers a[0..n) (:func:`prefix_sum`); returns Σ a. ``sums``
    holds at least SCAN_BLOCKS + 1 integers (made once by the caller)."""
    if n <= 0:
        return 0
    return int(prefix_sum(n, scan_block(n), a, sums, out))
