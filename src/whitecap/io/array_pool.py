"""Host arrays for frames handed out one after another, used again once nothing else holds them.

A stage that reads a frame back from the device every frame (the diffuse particles: 110 MB a frame at 2.7 M
of them) and hands it to the background writer cannot write the next frame into the same arrays: the writer
may still be packing them, and the state and the caller may keep them. New arrays every frame are new pages
every frame. Arrays this large are mapped afresh by the allocator each time (glibc maps anything above 32 MB
itself and unmaps it on free), so every frame faulted its pages in one by one and unmapped them again; on the
H100 machine fresh pages cost about ten times the copy into them (io/ply.py's record buffer: 180 ms a
100 MB file against 15 ms once the buffer was kept).

:class:`ArrayPool` keeps a few blocks of arrays and hands out views of their first ``n`` rows. A block is
taken again only when Python holds no reference to any of its arrays but the pool's own: every view of it
(the frame's arrays, slices of them, the writer's job, a read-back's pending copy) refers to its array, so a
frame that anyone still holds is never written over. When every kept block is busy, a new block is made
(kept while fewer than ``keep`` are): never a wait, never a shared frame.

Not for arrays whose memory is lent to foreign code that keeps a raw pointer without a Python reference
(ctypes addresses kept past the call): the pool cannot see those.

With ``pin`` and ``unpin`` (sim.runtime.host_pinning: the CUDA driver's cuMemHostRegister and
cuMemHostUnregister), a block is one page-aligned buffer of whole pages, its arrays views into it, pinned
once when made, so that the GPU's copies into it run by DMA instead of through the driver's staging buffer;
it is unpinned when the buffer is freed (the pool let it go and nothing else holds a view of it).
"""

from __future__ import annotations

import sys
import weakref
from typing import Callable, Mapping

import numpy as np

#: Blocks kept by default: the frame just made (the state's host view), the two the writer's lane is writing
#: (io.writer.LANE_DEPTH: frame k's file beside frame k-1's) and one waiting for the lane. A fifth frame in flight
#: gets a block of its own, as every frame did before.
KEEP = 4
#: Rows a block is made with, per row asked for: a count that grows (a splash's diffuse particles) would
#: otherwise need a new block every frame until it stops growing; more would hold more memory at the peak.
GROWTH = 1.125
#: Bytes of a page: a pinned block's buffer and each of its arrays start on one, and it holds whole pages (no
#: page of it shared with other memory, which the driver would pin along with it).
PAGE = 4096


class _Block:
    """A block's arrays by name, and the arrays that own its memory (the arrays themselves, or the one buffer
    they view when pinned), with the reference counts each has when nothing but the pool holds the block."""

    def __init__(self, arrays: dict[str, np.ndarray], owners: list[np.ndarray]) -> None:
        self.arrays, self.owners = arrays, owners
        self.rows = len(next(iter(arrays.values())))
        self.free_refs = [0] * len(owners)


class ArrayPool:
    """Blocks of host arrays of a fixed layout ({name: (dtype, shape of a row)}), handed out ``n`` rows at a
    time by :meth:`take`; with ``pin`` (address, bytes) -> whether pinned and ``unpin`` (address), page-locked."""

    def __init__(self, layout: Mapping[str, tuple[np.dtype | type, tuple[int, ...]]], keep: int = KEEP,
                 pin: Callable[[int, int], bool] | None = None, unpin: Callable[[int], object] | None = None) -> None:
        if keep < 1:
            raise ValueError("an ArrayPool keeps at least one block")
        self._layout = {k: (np.dtype(dt), tuple(int(s) for s in row)) for k, (dt, row) in layout.items()}
        self._keep = keep
        self._pin, self._unpin = pin, unpin
        self._blocks: list[_Block] = []
        self.made = 0  # blocks made so far (tests, benchmarks): it stops growing once the pool is warm
        self.pinned = 0  # blocks pinned so far

    def take(self, n: int) -> dict[str, np.ndarray]:
        """``n`` rows of each array of the layout (contiguous views of one block's arrays, contents as left by
        whatever used them last): of a kept block nothing else refers to and large enough, else of a new one."""
        n = int(n)
        free = [block for block in self._blocks if self._is_free(block)]
        for block in free:
            if block.rows >= n:
                return self._views(block, n)
        if free:  # free but all too small: the first makes room for a larger one (found by identity)
            self._blocks = [b for b in self._blocks if b is not free[0]]
        kept = len(self._blocks) < self._keep
        block = self._make(max(n, int(n * GROWTH)), pinned=kept)  # one not kept is not worth pinning
        if kept:
            self._blocks.append(block)
            block.free_refs = self._refs(block)
        return self._views(block, n)

    @property
    def nbytes(self) -> int:
        """Bytes held by the kept blocks."""
        return sum(o.nbytes for block in self._blocks for o in block.owners)

    def _make(self, rows: int, pinned: bool) -> _Block:
        self.made += 1
        if self._pin is None or not pinned:
            arrays = {k: np.empty((rows, *row), dt) for k, (dt, row) in self._layout.items()}
            return _Block(arrays, list(arrays.values()))
        nbytes = {k: rows * int(np.prod(row, dtype=np.int64)) * dt.itemsize for k, (dt, row) in self._layout.items()}
        offsets, size = {}, 0
        for k, b in nbytes.items():  # each array on whole pages of its own
            offsets[k] = size
            size += -(-b // PAGE) * PAGE or PAGE
        buf = np.empty(size + PAGE, np.uint8)
        start = -buf.ctypes.data % PAGE
        arrays = {k: buf[start + offsets[k]:start + offsets[k] + nbytes[k]].view(dt).reshape(rows, *row)
                  for k, (dt, row) in self._layout.items()}
        address = buf.ctypes.data + start
        if self._pin(address, size):
            self.pinned += 1
            if self._unpin is not None:
                weakref.finalize(buf, self._unpin, address).atexit = False  # once nothing views the buffer
        return _Block(arrays, [buf])

    @staticmethod
    def _views(block: _Block, n: int) -> dict[str, np.ndarray]:
        return {k: a[:n] for k, a in block.arrays.items()}

    @staticmethod
    def _refs(block: _Block) -> list[int]:
        return [sys.getrefcount(o) for o in block.owners]

    def _is_free(self, block: _Block) -> bool:
        """No reference to any of the block's memory but the pool's (a view refers to the array that owns the
        memory it views: the array itself, or a pinned block's buffer)."""
        return all(r <= free for r, free in zip(self._refs(block), block.free_refs))
