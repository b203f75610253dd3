"""Uniform-grid neighbour search, shared by the PBF solver and the foam stage.

Counting sort by cell (Green 2008, "Particle Simulation using CUDA"):

1. each particle finds its cell and takes a rank inside it with an atomic add;
2. an exclusive prefix sum over the cell counts gives each cell's start;
3. particles scatter to ``start[cell] + rank``; each cell's run is then
   sorted by particle index so the result does not depend on thread timing
   (bit-identical runs, resumes and foam whatever the thread count);
4. a fixed-capacity neighbour list per particle is filled by scanning the
   surrounding cells. Capacity is fixed, so memory never grows; overflow is
   counted and reported, never silently dropped.

The lists hold offsets j − i, not indices: neighbour k of particle i is
``neighbor(nb, i, k)`` = i + nb[i, k]. A grid made ``compact`` stores them in
16 bits: the solver keeps its particles in cell order (it reorders them every
few steps), so the offsets are small, and the lists take 2 bytes an entry
instead of 4 (128 B a particle at the default capacity of 64, not 256); a
particle's ~30 neighbours then lie in one cache line instead of two, and the
neighbour loops run 3–13 % faster (measured at 115k particles). Right after a
sort an offset is at most the number of particles in the 2·reach + 1 slices
of cells (along x, the outermost axis of the cell numbering) around a
particle's own (:func:`slice_span`); the solver makes its grid compact only
when that is at most half the 16-bit range, leaving the other half for the
particles' drift between reorders. An offset that does not fit anyway is never
truncated: the build counts such pairs and, when there are any, fills a
second set of lists with 32-bit offsets instead (allocated the first time it
is needed), which the kernels then read (:attr:`NeighborGrid.nb`; each
kernel compiles once per width).

The scan of the surrounding cells is written once, :func:`for_each_neighbor`:
the solver fills its lists with it and the diffuse stage asks it about points
that are not fluid particles.

Everything is a plain Taichi ndarray, so kernels compile once per process
whatever the particle count.
"""


import math
from dataclasses import dataclass

import numpy as np
import taichi as ti

from ..errors import WhitecapError

vec3 = ti.math.vec3
ivec3 = ti.math.ivec3
F1 = ti.types.ndarray(dtype=ti.f32, ndim=1)
F3 = ti.types.ndarray(dtype=vec3, ndim=1)
I1 = ti.types.ndarray(dtype=ti.i32, ndim=1)
# Neighbour lists: offsets j − i, 16-bit (or 32-bit when some do not fit; see the module docstring).
NB = ti.types.ndarray(ndim=2)
NARROW = ti.i16
NARROW_LIMIT = 2**15 - 1  # the largest |j − i| a 16-bit list holds
WIDE = ti.i32
WIDE_LIMIT = 2**31 - 1
SCAN_BLOCK = 1024  # cells per block of the two-level prefix sum
CORNER_SLACK = 0.01  # margin, in cells, of the corner-column test in for_each_neighbor


@ti.func
def cell_of(p: vec3, lower: vec3, inv_cell: ti.f32, dims: ivec3) -> ivec3:
    c = ti.cast(ti.floor((p - lower) * inv_cell), ti.i32)
    return ti.math.clamp(c, 0, dims - 1)


@ti.func
def cell_index(c: ivec3, dims: ivec3) -> ti.i32:
    return (c.x * dims.y + c.y) * dims.z + c.z


@ti.kernel
def _count_cells(
    n: ti.i32, x: F3, lower: vec3, inv_cell: ti.f32, dims: ivec3, cell: I1, rank: I1, count: I1
):
    for i in range(n):
        c = cell_index(cell_of(x[i], lower, inv_cell, dims), dims)
        cell[i] = c
        rank[i] = ti.atomic_add(count[c], 1)


@ti.kernel
def _clear(a: I1, n: ti.i32):
    for i in range(n):
        a[i] = 0


@ti.kernel
def _block_sums(count: I1, ncells: ti.i32, bsum: I1):
    for b in range(bsum.shape[0]):
        s = 0
        for k in range(SCAN_BLOCK):
            idx = b * SCAN_BLOCK + k
            if idx < ncells:
                s += count[idx]
        bsum[b] = s


@ti.kernel
def _scan_blocks(bsum: I1):
    ti.loop_config(serialize=True)
    run = 0
    for b in range(bsum.shape[0]):
        s = bsum[b]
        bsum[b] = run
        run += s


@ti.kernel
def _scan_cells(count: I1, ncells: ti.i32, bsum: I1, start: I1, n: ti.i32):
    for b in range(bsum.shape[0]):
        run = bsum[b]
        for k in range(SCAN_BLOCK):
            idx = b * SCAN_BLOCK + k
            if idx < ncells:
                start[idx] = run
                run += count[idx]
    start[ncells] = n


@ti.kernel
def _scatter(n: ti.i32, cell: I1, rank: I1, start: I1, order: I1):
    for i in range(n):
        order[start[cell[i]] + rank[i]] = i


@ti.kernel
def _sort_cells(ncells: ti.i32, start: I1, order: I1):
    # Insertion sort of each cell's short run by particle index: makes the
    # layout independent of the order in which atomics were granted.
    for c in range(ncells):
        a, b = start[c], start[c + 1]
        for k in range(a + 1, b):
            v = order[k]
            m = k - 1
            while m >= a and order[m] > v:
                order[m + 1] = order[m]
                m -= 1
            order[m + 1] = v


@ti.kernel
def gather_vec3(n: ti.i32, order: I1, src: F3, dst: F3):
    """dst[k] = src[order[k]]: a per-particle array put into cell order."""
    for k in range(n):
        dst[k] = src[order[k]]


@ti.kernel
def gather_i32(n: ti.i32, order: I1, src: I1, dst: I1):
    """dst[k] = src[order[k]] for an integer array."""
    for k in range(n):
        dst[k] = src[order[k]]


@ti.func
def for_each_neighbor(
    p: vec3, h: ti.f32, lower: ti.template(), inv_cell: ti.template(), dims: ti.template(), x_sorted: F3, start: I1,
    reach: ti.template(), task: ti.template(), args: ti.template(), every_candidate: ti.template(),
):
    """The one neighbour query: calls ``task(s, r², *args)`` for every particle
    within ``h`` of the point ``p`` (|x_s − p|² < h²), where ``s`` is the
    particle's slot in cell order (``order[s]`` its index, ``x_sorted[s]`` its
    position) and r² its squared distance. ``lower``, ``inv_cell``, ``dims``,
    ``x_sorted``, ``start`` and ``reach`` are those of a built
    :class:`NeighborGrid`, as :meth:`~NeighborGrid.query_args` gives them (a kernel
    takes them as arguments and hands them on: as templates they are not
    copied, which keeps the scan as fast as if it were written in the kernel).
    A point p falls in cell floor((p − lower)·inv_cell), clamped to [0, dims).
    ``args`` is a tuple handed on to ``task``; give its accumulators a
    ``ti.template()`` annotation in ``task`` so that they are updated in place.
    With ``every_candidate`` set (compile time), ``task`` is called for every
    candidate in the scanned cells, r² ≥ h² included, and tests r² itself: a
    task that can do so without a branch avoids mispredicting it (see
    :func:`_build_lists`).

    Cells are h/reach wide, so the search covers (2·reach + 1)³ cells; the cells
    along z of each (x, y) column are adjacent in the cell numbering, so one
    contiguous run of the sorted order covers them, read from memory in order.
    The loop over x is unrolled at compile time. In the two outer x slices
    (dx = ±reach) the corner columns (dy = ±reach) are left out when their
    nearest edge is at least h from ``p`` in x-y, which happens about two times
    in three for points spread evenly in their cell: with cells of h/2 that is
    about 11 % of the candidates, and building the solver's lists took
    about 10 % less time (measured at 115k particles)."""
    c = cell_of(p, lower, inv_cell, dims)
    z0 = ti.max(c.z - reach, 0)
    z1 = ti.min(c.z + reach, dims.z - 1)
    h2 = h * h
    w = 1.0 / inv_cell  # cell width
    f = p - (lower + ti.cast(c, ti.f32) * w)  # p's offset inside its cell
    # Corner test with h grown by a hundredth of a cell, so that rounding in f never drops a column holding a neighbour.
    h_corner2 = (h + CORNER_SLACK * w) ** 2
    for dx in ti.static(range(-reach, reach + 1)):
        cx = c.x + dx
        if 0 <= cx < dims.x:
            y0 = c.y - reach
            y1 = c.y + reach
            if ti.static(abs(dx) == reach):
                # Distances from p to the x slice and to the outer y columns' nearest edges.
                ex = (-dx - 1) * w + f.x
                if ti.static(dx > 0):
                    ex = dx * w - f.x
                ey_lo = (reach - 1) * w + f.y
                ey_hi = reach * w - f.y
                if ex * ex + ey_lo * ey_lo >= h_corner2:
                    y0 += 1
                if ex * ex + ey_hi * ey_hi >= h_corner2:
                    y1 -= 1
            for cy in range(ti.max(y0, 0), ti.min(y1, dims.y - 1) + 1):
                first = start[cell_index(ivec3(cx, cy, z0), dims)]
                last = start[cell_index(ivec3(cx, cy, z1), dims) + 1]
                for s in range(first, last):
                    r2 = (x_sorted[s] - p).norm_sqr()
                    if ti.static(every_candidate):
                        task(s, r2, *args)
                    elif r2 < h2:
                        task(s, r2, *args)


@ti.func
def _append_slot(s, r2, si, h2, buf: ti.template(), cap: ti.template(), k: ti.template()):
    """Branch-free append of candidate slot ``s`` to the local list ``buf``: the slot is
    always written at ``k`` (at ``cap``, a sink, once the list is full) and ``k``
    advances only when the candidate is within h (r² < h²) and is not the particle
    itself (slot ``si``). ``k`` keeps counting past ``cap``: the excess is the overflow."""
    buf[ti.min(k, cap)] = s
    k += ti.select((r2 < h2) & (s != si), 1, 0)


@ti.func
def neighbor(nb: ti.template(), i, k):
    """Index j of the ``k``-th neighbour of particle ``i``: the lists hold j − i."""
    return i + ti.cast(nb[i, k], ti.i32)


@ti.kernel
def _build_lists(
    n: ti.i32, lower: vec3, inv_cell: ti.f32, dims: ivec3, x_sorted: F3, start: I1, reach: ti.template(), h: ti.f32,
    order: I1, nb_count: I1, nb: NB, cap: ti.template(), dt: ti.template(), limit: ti.i32,
) -> ivec3:
    """Fills the lists of every particle i with the offsets j − i of its
    neighbours j (nb[i, :nb_count[i]], element type ``dt``), in the order
    :func:`for_each_neighbor` meets them. Returns (how many neighbours did not
    fit in the capacity, how many offsets exceed ``limit`` in size, 0); when
    the second is not zero the lists are unusable and the caller builds them
    again wider.

    Every candidate is handled without a branch on its distance
    (:func:`_append_slot`), into a list local to the thread (``cap`` + 1 slots
    on the stack), which is then copied out: once the starting lattice has
    disordered, about a third of the ~115 candidates a particle are neighbours,
    in no pattern the processor can predict, and the branch per candidate made
    this kernel 2.4× slower than on the lattice. Measured at 115k particles:
    16 → 20 ms on the lattice (step 5), 40 → 27 ms at step 70. Stores into the
    local list, unlike stores into ``nb``, cannot alias the grid arrays, so
    their loads stay hoisted out of the candidate loop."""
    overflow = 0
    far = 0
    for si in range(n):
        # Walk particles in cell order: consecutive iterations share their
        # candidate cells, which then stay in cache.
        i = order[si]
        k = 0
        h2 = h * h
        buf = ti.Vector([0] * (cap + 1), dt=ti.i32)  # candidate slots; buf[cap] takes the overflow
        for_each_neighbor(
            x_sorted[si], h, lower, inv_cell, dims, x_sorted, start, reach, _append_slot, (si, h2, buf, cap, k), True
        )
        m = ti.min(k, cap)
        for q in range(m):
            d = order[buf[q]] - i
            far += ti.select(ti.abs(d) > limit, 1, 0)
            nb[i, q] = ti.cast(d, dt)
        nb_count[i] = m
        overflow += k - m
    return ivec3(overflow, far, 0)


@dataclass
class GridSpec:
    lower: tuple[float, float, float]
    cell: float
    dims: tuple[int, int, int]

    @property
    def ncells(self) -> int:
        return self.dims[0] * self.dims[1] * self.dims[2]


def grid_spec(lower, upper, cell: float, max_cells: int = 64_000_000) -> GridSpec:
    dims = tuple(max(1, int(math.ceil((u - lo) / cell))) for lo, u in zip(lower, upper))
    spec = GridSpec(tuple(float(v) for v in lower), float(cell), dims)  # type: ignore[arg-type]
    if spec.ncells > max_cells:
        raise WhitecapError(
            f"neighbour grid of {dims} cells is too large; the domain is huge compared with the kernel support"
        )
    return spec


class NeighborGrid:
    """Cell-sorted particle order plus fixed-capacity neighbour lists.

    After :meth:`build`, ``order[start[c]:start[c+1]]`` are the particles in
    cell ``c`` and ``i + nb[i, :nb_count[i]]`` the neighbours of particle ``i``
    within ``h`` (excluding ``i`` itself; kernels read them with
    :func:`neighbor`, Python with :meth:`lists`). Kernels query the grid around
    any point with :func:`for_each_neighbor` and :meth:`query_args`.

    With ``compact`` unset the lists are 32-bit from the start. With it set,
    ``nb`` is the 16-bit set of lists, or the 32-bit one (``wide`` True) when
    some offset did not fit: ``far`` counts those offsets in the last build,
    whichever set it filled, so it depends only on the positions and the
    particle order. A build after one with ``far`` > 0 goes straight to 32 bits
    (no wasted 16-bit attempt while the particles stay out of order); once the
    offsets fit again, the next build is 16-bit. ``offset_limit`` is the
    largest offset the 16-bit lists may take (lowered by tests to force the
    32-bit path).
    """

    def __init__(self, spec: GridSpec, capacity: int, max_neighbors: int, h: float, compact: bool = False):
        self.spec = spec
        # Cells of h/2 test ~125/216 as many candidates as cells of h (measured
        # ~25 % faster list building); coarser cells are searched with reach 1.
        self.reach = reach_for(spec, h)
        self.h = float(h)
        self.capacity = int(capacity)
        self.max_neighbors = int(max_neighbors)
        nc = spec.ncells
        self.cell = ti.ndarray(ti.i32, capacity)
        self.rank = ti.ndarray(ti.i32, capacity)
        self.order = ti.ndarray(ti.i32, capacity)
        self.count = ti.ndarray(ti.i32, nc)
        self.start = ti.ndarray(ti.i32, nc + 1)
        self.bsum = ti.ndarray(ti.i32, (nc + SCAN_BLOCK - 1) // SCAN_BLOCK)
        self.nb_count = ti.ndarray(ti.i32, capacity)
        self.compact = bool(compact)
        # 16-bit lists when compact; 32-bit ones from the start otherwise, or from the first build that needs them.
        self.nb_narrow = ti.ndarray(NARROW, (capacity, max_neighbors)) if self.compact else None
        self.nb_wide = None if self.compact else ti.ndarray(WIDE, (capacity, max_neighbors))
        self.wide = not self.compact  # nb is nb_wide
        self.far = 0  # offsets over offset_limit in the last build
        self.try_narrow = self.compact  # compact, and the last build's offsets fitted: try 16 bits first
        self.offset_limit = NARROW_LIMIT if self.compact else WIDE_LIMIT
        self.x_sorted = ti.Vector.ndarray(3, ti.f32, capacity)
        self.overflow = 0
        self.lower = vec3(*spec.lower)
        self.inv_cell = 1.0 / spec.cell
        self.dims = ivec3(*spec.dims)

    @property
    def nb(self):
        """The lists the last :meth:`build` filled: 16-bit, or 32-bit when ``wide``."""
        return self.nb_wide if self.wide else self.nb_narrow

    def nbytes(self) -> int:
        nc = self.spec.ncells
        entry = (2 if self.nb_narrow is not None else 0) + (4 if self.nb_wide is not None else 0)
        lists = self.capacity * self.max_neighbors * entry
        return 4 * (self.capacity * 7 + 2 * nc + 1 + len_blocks(nc)) + lists

    def lists(self, n: int) -> tuple:
        """(counts, neighbour indices) of the first ``n`` particles as NumPy arrays, the indices
        absolute (i + offset); entries past a particle's count are meaningless."""
        counts = self.nb_count.to_numpy()[:n]
        return counts, self.nb.to_numpy()[:n].astype(np.int64) + np.arange(n)[:, None]

    def sort(self, x, n: int) -> None:
        """Counting sort of the first ``n`` positions of ``x`` into cells."""
        s = self.spec
        _clear(self.count, s.ncells)
        _count_cells(n, x, self.lower, self.inv_cell, self.dims, self.cell, self.rank, self.count)
        _block_sums(self.count, s.ncells, self.bsum)
        _scan_blocks(self.bsum)
        _scan_cells(self.count, s.ncells, self.bsum, self.start, n)
        _scatter(n, self.cell, self.rank, self.start, self.order)
        _sort_cells(s.ncells, self.start, self.order)

    def build(self, x, n: int) -> int:
        """Sort and fill neighbour lists; returns how many neighbours overflowed."""
        self.sort(x, n)
        gather_vec3(n, self.order, x, self.x_sorted)
        args = (n, *self.query_args(), self.h, self.order, self.nb_count)
        self.wide = not self.try_narrow
        if self.try_narrow:
            r = _build_lists(*args, self.nb_narrow, self.max_neighbors, NARROW, self.offset_limit)
            self.wide = int(r[1]) > 0
        if self.wide:  # some offset needs (or last time needed) more than 16 bits: the same lists, 32-bit
            if self.nb_wide is None:
                self.nb_wide = ti.ndarray(WIDE, (self.capacity, self.max_neighbors))
            r = _build_lists(*args, self.nb_wide, self.max_neighbors, WIDE, self.offset_limit)
        self.far = int(r[1])
        self.try_narrow = self.far == 0
        self.overflow = int(r[0])
        return self.overflow

    def query_args(self) -> tuple:
        """(lower, inv_cell, dims, x_sorted, start, reach): what a kernel hands
        :func:`for_each_neighbor` to search this grid after :meth:`build`."""
        return self.lower, self.inv_cell, self.dims, self.x_sorted, self.start, self.reach


def reach_for(spec: GridSpec, h: float) -> int:
    """How many cells the search reaches out along each axis: h / cell, at least 1."""
    return max(1, int(round(h / spec.cell)))


def slice_span(positions: np.ndarray, spec: GridSpec, reach: int) -> int:
    """The most particles in 2·reach + 1 consecutive x slices of cells: right after a sort
    into cell order, no neighbour list holds an offset |j − i| larger than this."""
    if len(positions) == 0:
        return 0
    cx = np.floor((positions[:, 0] - spec.lower[0]) / spec.cell).astype(np.int64)
    pop = np.bincount(np.clip(cx, 0, spec.dims[0] - 1), minlength=spec.dims[0])
    return int(np.convolve(pop, np.ones(2 * reach + 1, np.int64)).max())


def len_blocks(nc: int) -> int:
    return (nc + SCAN_BLOCK - 1) // SCAN_BLOCK
