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
"""

from __future__ import annotations

import sys
from typing import Mapping

import numpy as np

#: Blocks kept by default: the frame just made (the state's host view), the one the writer's thread is writing
#: and one waiting in its queue (io.writer.DEFAULT_QUEUE jobs, of which a frame's other files take some). A
#: fourth frame in flight gets a block of its own, as every frame did before.
KEEP = 3
#: Rows a block is made with, per row asked for: a count that grows (a splash's diffuse particles) would
#: otherwise need a new block every frame until it stops growing; more would hold more memory at the peak.
GROWTH = 1.125


class ArrayPool:
    """Blocks of host arrays of a fixed layout ({name: (dtype, shape of a row)}), handed out ``n`` rows at a
    time by :meth:`take`."""

    def __init__(self, layout: Mapping[str, tuple[np.dtype | type, tuple[int, ...]]], keep: int = KEEP) -> None:
        if keep < 1:
            raise ValueError("an ArrayPool keeps at least one block")
        self._layout = {k: (np.dtype(dt), tuple(int(s) for s in row)) for k, (dt, row) in layout.items()}
        self._keep = keep
        self._blocks: list[dict[str, np.ndarray]] = []
        self._free_refs: int | None = None  # sys.getrefcount of a kept block's array that nothing else holds
        self.made = 0  # blocks made so far (tests, benchmarks): it stops growing once the pool is warm

    def take(self, n: int) -> dict[str, np.ndarray]:
        """``n`` rows of each array of the layout (contiguous views of one block's arrays, contents as left by
        whatever used them last): of a kept block nothing else refers to and large enough, else of a new one."""
        n = int(n)
        free = [block for block in self._blocks if self._is_free(block)]
        for block in free:
            if self._rows(block) >= n:
                return self._views(block, n)
        if free:  # free but all too small: the first makes room for a larger one (found by identity: the
            # blocks' arrays do not compare as booleans)
            self._blocks = [b for b in self._blocks if b is not free[0]]
        block = self._make(max(n, int(n * GROWTH)))
        if len(self._blocks) < self._keep:
            self._blocks.append(block)
            if self._free_refs is None:
                self._free_refs = self._refs(block)
        return self._views(block, n)

    @property
    def nbytes(self) -> int:
        """Bytes held by the kept blocks."""
        return sum(a.nbytes for block in self._blocks for a in block.values())

    def _make(self, rows: int) -> dict[str, np.ndarray]:
        self.made += 1
        return {k: np.empty((rows, *row), dt) for k, (dt, row) in self._layout.items()}

    @staticmethod
    def _rows(block: dict[str, np.ndarray]) -> int:
        return len(next(iter(block.values())))

    def _views(self, block: dict[str, np.ndarray], n: int) -> dict[str, np.ndarray]:
        return {k: a[:n] for k, a in block.items()}

    @staticmethod
    def _refs(block: dict[str, np.ndarray]) -> int:
        return max(sys.getrefcount(a) for a in block.values())

    def _is_free(self, block: dict[str, np.ndarray]) -> bool:
        """No reference to any of the block's arrays but the pool's (a view refers to the array it views)."""
        return all(sys.getrefcount(a) <= (self._free_refs or 0) for a in block.values())
