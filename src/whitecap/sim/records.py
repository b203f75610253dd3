"""A frame's particles made on the device as the vertex records of its PLY file, and read back in one piece.

The PLY writer (io.ply) packs a frame's arrays into records (``x y z vx vy vz ...``, little-endian, no gaps) before
it writes them. Made by a kernel where the particles are (the solver's fluid, the foam stage's diffuse particles),
the records come back from the GPU in one copy, or on the CPU are written by the kernel straight into host memory,
and the writer writes them as they are (ParticleFrame.from_records, io.ply's records test): no packing on the host,
where the writer's threads took 35-40 ms of a 16-core machine for a 1 M fluid file and about as long again for
its diffuse one beside the simulation loop (benchmarks/RESULTS.md, issue 31).

- :func:`record_packer`: the kernel for a record layout, a whole number of 32-bit words a thread;
- :class:`RecordReader`: a frame's records through it, into a host block of an io.array_pool pool, on any arch.

:data:`WORDS_MAX` caps the words one frame's records may take (a Taichi array's elements are counted in int32):
callers read a larger frame back array by array instead, and the writer packs it, as before.
"""


import functools
import math
from typing import Any, Callable

import numpy as np
import taichi as ti

from ..io import ParticleFrame
from ..io.array_pool import ArrayPool
from . import runtime
from .grid import F1, F3, U1
from .launch import TEMPLATE

#: The most 32-bit words one frame's records are made into (a Taichi array's elements are counted in int32).
#: Above it (232 M diffuse particles, 268 M fluid particles) a frame is read back array by array. 0: every frame
#: is (the benchmarks' ``--arrays``, and the tests' way of comparing the two).
WORDS_MAX = 2**31 - 1
#: Words a ti.static loop of a packer unrolls at most (Taichi warns past its unrolling limit, 32)
_UNROLLED_WORDS = 24
#: Where a record's field comes from, in a packer's arguments: ``a`` and ``b`` the two float32 3-vectors (the
#: component given), ``c`` the float32 column, ``d`` and ``e`` the two 32-bit integer columns (their bits; a field
#: of one byte takes the low byte), ``const`` the one value every record has (its bits an argument).
SOURCES = ("a", "b", "c", "d", "e", "const")
N1: Any = ti.types.ndarray(ndim=1)  # a 32-bit integer column of either signedness


def record_packer(record: np.dtype, sources: dict[str, tuple[str, int]]) -> tuple[Callable, int, int]:
    """(kernel, records a thread, 32-bit words a thread) making records of the numpy dtype ``record`` (a PLY
    vertex record: io.ply.record_dtype; little-endian fields of 1 or 4 bytes at their offsets, no gaps), each field
    from ``sources[name]`` = (source, component) (:data:`SOURCES`): the bytes the PLY writer would pack from the
    arrays.

    ``kernel(n, a, b, c, d, e, const_bits, out)`` makes records 0..n: each thread G consecutive records, a whole
    number of 32-bit words (G = 4 for a 37-byte record: 148 bytes, 37 words; G = 1 for 32 bytes), each word put
    together from the fields it overlaps (a field split across two words lands in both, shifted) and stored once,
    into out[0 .. ceil(n/G)·W) of a uint32 array; the last thread's records past n are left zero and none of their
    rows read. The make-up of every word is fixed when the kernel is compiled, so a word is a few shifts and ors of
    values the thread loaded: a quarter of the stores of writing a 37-byte record a byte at a time (1.6 against
    3.5 ms for 273k records on 2 cores), and whole words on a GPU. Sources a layout does not use may be any array
    of their type (they are not read).

    The kernel is made once a process for a layout: every reader of it (a run's solver and foam stage, a
    benchmark's warm-up and timed runs, each test's) shares it. A kernel made anew is compiled anew: 210 ms on 2
    cores for the diffuse record, each time a FoamGenerator or PBFSolver was made (Taichi's offline cache did not
    keep it), which a benchmark's timed run paid after its warm-up."""
    return _made_packer(np.dtype(record), tuple(sorted(sources.items())))


@functools.lru_cache(maxsize=None)
def _made_packer(record: np.dtype, source_items: tuple[tuple[str, tuple[str, int]], ...]) -> tuple[Callable, int, int]:
    """:func:`record_packer`'s kernel, made for the layout (its sources as sorted items: hashable)."""
    sources = dict(source_items)
    size = int(record.itemsize)
    fields = sorted(((name, int(f[1]), int(f[0].itemsize)) for name, f in (record.fields or {}).items()),
                    key=lambda t: t[1])
    if (sum(sz for _, _, sz in fields) != size or any(sz not in (1, 4) or name not in sources for name, _, sz in fields)
            or any(src not in SOURCES for src, _ in sources.values())):
        raise ValueError(f"record_packer: a record of {record} is not one it can make from {sources}")
    per = 4 // math.gcd(size, 4)  # records a thread: a whole number of words
    words = per * size // 4
    plan: list[list[tuple[int, str, int, int, int]]] = []  # a word's parts: (record, source, component, bytes, shift)
    for w in range(words):
        parts = []
        for r in range(per):
            for name, off, sz in fields:
                at = r * size + off
                if at < 4 * w + 4 and at + sz > 4 * w:
                    src, comp = sources[name]
                    parts.append((r, src, comp, sz, 8 * (at - 4 * w)))  # shifted left (> 0) or right (< 0)
        plan.append(parts)
    chunks = [plan[i:i + _UNROLLED_WORDS] for i in range(0, words, _UNROLLED_WORDS)]
    firsts = list(range(0, words, _UNROLLED_WORDS))

    @ti.func
    def _bits(a: TEMPLATE, b: TEMPLATE, c: TEMPLATE, d: TEMPLATE, e: TEMPLATE, const_bits, p, src: TEMPLATE,
              comp: TEMPLATE, nbytes: TEMPLATE):
        bits = ti.u32(0)
        if ti.static(src == "a"):
            bits = ti.bit_cast(a[p][comp], ti.u32)
        elif ti.static(src == "b"):
            bits = ti.bit_cast(b[p][comp], ti.u32)
        elif ti.static(src == "c"):
            bits = ti.bit_cast(c[p], ti.u32)
        elif ti.static(src == "d"):
            bits = ti.cast(d[p], ti.u32)
        elif ti.static(src == "e"):
            bits = ti.cast(e[p], ti.u32)
        else:
            bits = const_bits
        if ti.static(nbytes == 1):
            bits &= ti.u32(0xFF)
        return bits

    @ti.kernel
    def pack_records(n: ti.i32, a: F3, b: F3, c: F1, d: N1, e: N1, const_bits: ti.u32, out: U1):
        for g in range((n + per - 1) // per):
            for h in ti.static(range(len(chunks))):
                for k in ti.static(range(len(chunks[h]))):
                    word = ti.u32(0)
                    for r, src, comp, nbytes, shift in ti.static(chunks[h][k]):
                        p = g * per + r
                        if p < n:
                            bits = _bits(a, b, c, d, e, const_bits, p, src, comp, nbytes)
                            if ti.static(shift >= 0):
                                word |= bits << ti.u32(shift)
                            else:
                                word |= bits >> ti.u32(-shift)
                    out[g * words + firsts[h] + k] = word

    return pack_records, per, words


class RecordReader:
    """A frame's records made by one :func:`record_packer` kernel and read back into host blocks of an
    io.array_pool pool (used again once no frame handed out holds them; page-locked where the pool's ``pin`` does).
    On a GPU the kernel writes a device array, made once at the capacity the caller gives (within
    :data:`WORDS_MAX`) and grown only if a frame needs more, then one copy brings the block back; on the CPU the
    kernel writes the host block in place."""

    def __init__(self, record: np.dtype, sources: dict[str, tuple[str, int]], pin=None, unpin=None) -> None:
        self.record = record
        self.pack, self.per, self.words = record_packer(record, sources)
        self.pool = ArrayPool({"records": (np.uint32, (self.words,))}, pin=pin, unpin=unpin)
        self.device: Any = None  # the device array (a GPU's), once made

    def words_for(self, n: int) -> int:
        """32-bit words of n records."""
        return -(-n // self.per) * self.words

    def fits(self, n: int) -> bool:
        """Whether n records fit in one Taichi array (:data:`WORDS_MAX`)."""
        return self.words_for(n) <= WORDS_MAX

    @property
    def nbytes(self) -> int:
        """Bytes of the device array."""
        return 0 if self.device is None else 4 * int(self.device.shape[0])

    def read(self, n: int, args: tuple, capacity: int, later: bool = False):
        """(the frame of records 0..n, made from ``args`` (a, b, c, d, e, const_bits), the pending copy's Future
        where ``later`` left it running on CUDA (runtime.rows_to_host_later), else None). ``capacity``: the most
        records the caller's frames hold, which the device array is made for."""
        block = self.pool.take(-(-n // self.per))["records"].reshape(-1)
        pending = None
        if n:
            if runtime.copies_rows():  # made on the device, then one copy (runtime.rows_to_host)
                if self.device is None or self.device.shape[0] < len(block):
                    self.device = None  # the old array goes before the new one is made
                    self.device = runtime.empty_ndarray(
                        ti.u32, max(len(block), min(self.words_for(capacity), WORDS_MAX)))
                self.pack(n, *args, self.device)
                if later:
                    pending = runtime.rows_to_host_later((block, self.device))
                if pending is None and not runtime.rows_to_host((block, self.device)):
                    block[:] = self.device.to_numpy()[:len(block)]
            else:  # a host array: on the CPU the kernel writes it in place
                self.pack(n, *args, block)
        return ParticleFrame.from_records(block.view(np.uint8)[:n * self.record.itemsize].view(self.record)), pending
