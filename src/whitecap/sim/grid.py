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

The scan of the surrounding cells is written once, :func:`for_each_neighbor`:
the solver fills its lists with it and the diffuse stage asks it about points
that are not fluid particles.

Two layouts of the cell table, chosen per grid (:func:`grid_layout`):

- *dense*: one entry per cell of the domain, cells numbered column by column
  along z, so the cells of a column are one contiguous run of the sorted order.
  Fastest, but its size follows the domain's volume, not the particles;
- *hashed*, when the domain has many more cells than there are particles (a
  small wave in a coastal box): a power-of-two table of buckets sized from the
  particle capacity (Teschner et al. 2003, "Optimized Spatial Hashing for
  Collision Detection of Deformable Objects"). Cell (x, y, z) goes to bucket
  (H(x, y) + z) mod T, so that, as in the dense table, the cells of a column
  are consecutive buckets and one contiguous run (two where it wraps round the
  table's end). The counting sort is by bucket, each bucket's run is sorted by
  (cell key, particle index), and a query skips the particles of other cells
  that share a bucket, recomputing their cell from their position exactly as
  the sort did: each neighbouring cell is visited once, no particle twice.
  Memory is proportional to the capacity; the domain's size only bounds the
  cell coordinates (:data:`MAX_AXIS_CELLS`).

Points outside the domain belong to the nearest border cell (clamped), in both
layouts: a query then finds every particle within h wherever the two lie, since
clamping never moves two cells further apart.

Everything is a plain Taichi ndarray, so kernels compile once per process
whatever the particle count.
"""


import functools
import math
from dataclasses import dataclass
from typing import Any, NamedTuple

import taichi as ti

from ..errors import WhitecapError
from . import runtime
from .launch import TEMPLATE, KernelGraph, run_direct

# Taichi's vector types and kernel argument annotations (typed Any: they are not Python types).
vec3: Any = ti.math.vec3
ivec3: Any = ti.math.ivec3
F1: Any = ti.types.ndarray(dtype=ti.f32, ndim=1)
F3: Any = ti.types.ndarray(dtype=vec3, ndim=1)
I1: Any = ti.types.ndarray(dtype=ti.i32, ndim=1)
I2: Any = ti.types.ndarray(dtype=ti.i32, ndim=2)
U1: Any = ti.types.ndarray(dtype=ti.u32, ndim=1)  # ids as the files hold them
SCAN_BLOCK = 1024  # cells per block of the two-level prefix sum
#: On a GPU the block sums are scanned in groups of SCAN_GROUP_GPU, one thread a group, then the groups' totals by
#: one thread (sim.scan does the same): one GPU thread walking them one load at a time took the longest of the
#: sort's passes at 10 M particles and more (48,800 block sums at 10 M, 244,000 at 50 M in the dense table). The
#: CPU walks them in one thread, as before (a few hundred to a few thousand sums: microseconds).
SCAN_GROUP_GPU = 512
#: Block sums scanned in groups: None on a GPU only; True or False on any arch (tests of the GPU's layout on the CPU).
GROUPED_SCAN: bool | None = None
CORNER_SLACK = 0.01  # margin, in cells, of the corner-column test in for_each_neighbor
#: Hash buckets per particle of capacity, at least (the table is the next power of two, 8–16 per
#: particle, 32–64 B). At most one cell is occupied per particle (about one in the bulk: cells of h/2 =
#: 2r, the particle spacing), so at most 1/8 of the buckets are, and few particles of other cells share
#: a scanned bucket. Measured on the 120k dam break (jittered lattice, 2 cores, list building, CPU
#: time): 2 buckets a particle 57 ms, 4: 44, 8: 37, 16: 35, 32: 36; the dense table 21.5.
BUCKETS_PER_PARTICLE = 8
#: The dense table is used while the domain has at most DENSE_CELLS_PER_PARTICLE cells per particle
#: of capacity: 4 B a cell, so at most 128 B a particle (the solver's own arrays are about 380), still
#: in proportion to the particles. It builds the lists faster (1.6× in the measurement above: its
#: columns are runs of their own, with no other cells' particles to skip) and the foam stage's
#: queries about 2× faster (bench_foam's synthetic 100k: classify_candidates 50 against 112 ms,
#: advect_diffuse 58 against 106). Every imported sequence's domain (io.run.DOMAIN_RULE: twice the
#: frames' box along each axis) is 8 times their box, about 15 times the fluid's volume, so it is
#: kept up to a domain of about 32 times the fluid's volume (one cell a particle in the bulk: cells
#: of h/2 = 2r, the particle spacing). The benchmark's dam-break tank is 5.3 times it; a small wave in
#: a coastal box (1000 times) is hashed.
DENSE_CELLS_PER_PARTICLE = 32
#: Dense whatever the capacity up to this many cells (256 KiB of table): small grids, few particles.
DENSE_ALWAYS_CELLS = 1 << 16
#: Fewest buckets: more than the cells along z that one column query spans (2·reach + 1 plus the spread
#: of a group of points), so that a column's buckets never wrap onto themselves.
MIN_BUCKETS = 1024
#: Most cells along one axis: cell coordinates stay exact in f32 and i32, and a cell's key,
#: (x·ny + y)·nz + z, in i64 (below (2^21)³ = 2^63).
MAX_AXIS_CELLS = 1 << 21
#: The column hash H(x, y) (Teschner 2003 multiplies each coordinate by a large odd number and
#: combines them with xor; the result is then mixed so that its low bits, the bucket, depend on all bits).
HASH_X = 0x9E3779B1  # 2^32 / golden ratio, odd
HASH_Y = 0x85EBCA77  # odd, with well spread bits
HASH_MIX = 0x2C1B3C6D  # odd
#: Stands for r² of a particle that a hashed query skips (another cell's, sharing a bucket): never < h².
FAR2 = 3.0e38


@dataclass(frozen=True)
class Scan:
    """How :func:`for_each_neighbor` scans a grid, fixed at compile time (a kernel takes it as a
    ``ti.template()``, the last entry of :meth:`NeighborGrid.query_args`): ``reach`` cells each way
    (cells are h/reach wide), through the dense or the hashed cell table."""

    reach: int
    hashed: bool = False


#: The grid's query arguments, one kernel argument (a Taichi argument pack; its arrays are bound, not
#: copied): the domain's lower corner [m], 1 / cell width [1/m], the cells along x, y, z, the positions in
#: cell order and each table entry's first slot. :meth:`NeighborGrid.query_args` gives the grid's own.
GridQuery: Any = ti.types.argpack(lower=vec3, inv_cell=ti.f32, dims=ivec3, x_sorted=F3, start=I1)


class LooseQuery(NamedTuple):
    """The members of a :data:`GridQuery` from loose kernel arguments (handed on as ``ti.static``), for
    kernels launched in a compute graph."""

    lower: Any
    inv_cell: Any
    dims: Any
    x_sorted: Any
    start: Any


@ti.func
def cell_of(p: vec3, lower: vec3, inv_cell: ti.f32, dims: ivec3) -> ivec3:
    """The cell of point p, floor((p − lower)·inv_cell), clamped to [0, dims): points outside the
    domain belong to the nearest border cell. Clamped before the conversion to integers, so that a
    point however far away never overflows it (the same as clamping after it: the bounds are whole)."""
    f = ti.math.clamp((p - lower) * inv_cell, 0.0, ti.cast(dims - 1, ti.f32))
    return ti.cast(ti.floor(f), ti.i32)


@ti.func
def cell_index(c: ivec3, dims: ivec3) -> ti.i32:
    return (c.x * dims.y + c.y) * dims.z + c.z


@ti.func
def cell_key(c: ivec3, dims: ivec3) -> ti.i64:
    """The cell's number in the whole domain, (x·ny + y)·nz + z, in 64 bits (a hashed grid's cells
    can be far more than 2^31): the order of a hashed bucket's cells."""
    return (ti.cast(c.x, ti.i64) * dims.y + c.y) * dims.z + c.z


@ti.func
def column_hash(cx: ti.i32, cy: ti.i32) -> ti.u32:
    """H(x, y) of a column of cells; its cell z goes to bucket (H + z) mod T."""
    k = (ti.cast(cx, ti.u32) * ti.u32(HASH_X)) ^ (ti.cast(cy, ti.u32) * ti.u32(HASH_Y))
    k ^= k >> 15
    k *= ti.u32(HASH_MIX)
    k ^= k >> 13
    return k


@ti.func
def bucket_of(c: ivec3, mask: ti.i32) -> ti.i32:
    """The hashed table's bucket of cell c (T = mask + 1 buckets, a power of two)."""
    return ti.cast((column_hash(c.x, c.y) + ti.cast(c.z, ti.u32)) & ti.cast(mask, ti.u32), ti.i32)


@ti.kernel
def _count_cells(
    n: ti.i32, x: F3, lower: vec3, inv_cell: ti.f32, dims: ivec3, cell: I1, rank: I1, table: I1
):
    """Step 1: cell[i] is particle i's cell, rank[i] its rank in it, table[c] the cell's count."""
    for i in range(n):
        c = cell_index(cell_of(x[i], lower, inv_cell, dims), dims)
        cell[i] = c
        rank[i] = ti.atomic_add(table[c], 1)


@ti.kernel
def _count_buckets(
    n: ti.i32, x: F3, lower: vec3, inv_cell: ti.f32, dims: ivec3, cell: I1, rank: I1, table: I1
):
    """The hashed table's step 1: cell[i] is particle i's bucket, rank[i] its rank in it."""
    mask = table.shape[0] - 2  # T − 1: the table has T + 1 entries
    for i in range(n):
        b = bucket_of(cell_of(x[i], lower, inv_cell, dims), mask)
        cell[i] = b
        rank[i] = ti.atomic_add(table[b], 1)


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
def _scan_blocks(bsum: I1, gsum: I1, group: TEMPLATE):
    """The block sums become their blocks' starts (exclusive prefix sum): by one thread where ``group`` is 0;
    else within groups of ``group`` blocks, one thread a group, each group's total into gsum[g], then gsum
    scanned by one thread (_scan_cells adds a block's group start to its own)."""
    if ti.static(group == 0):
        ti.loop_config(serialize=True)
        run = 0
        for b in range(bsum.shape[0]):
            s = bsum[b]
            bsum[b] = run
            run += s
    else:
        nb = bsum.shape[0]
        for g in range((nb + group - 1) // group):
            t = 0
            for b in range(g * group, ti.min(nb, (g + 1) * group)):
                c = bsum[b]
                bsum[b] = t
                t += c
            gsum[g] = t
        ti.loop_config(serialize=True)
        run = 0
        for g in range((nb + group - 1) // group):
            s = gsum[g]
            gsum[g] = run
            run += s


@ti.kernel
def _scan_cells(table: I1, ncells: ti.i32, bsum: I1, gsum: I1, n: ti.i32, group: TEMPLATE):
    """Step 2, in place: the cells' counts become their starts (exclusive prefix sum); table[ncells] = n."""
    for b in range(bsum.shape[0]):
        run = bsum[b]
        if ti.static(group > 0):
            run += gsum[b // group]
        for k in range(SCAN_BLOCK):
            idx = b * SCAN_BLOCK + k
            if idx < ncells:
                c = table[idx]
                table[idx] = run
                run += c
    table[ncells] = n


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
def _sort_buckets(
    nbuckets: ti.i32, start: I1, order: I1, x: F3, lower: vec3, inv_cell: ti.f32, dims: ivec3
):
    # Insertion sort of each bucket's short run by (cell key, particle index): the cells sharing
    # the bucket each become one run, and the layout is independent of thread timing.
    for b in range(nbuckets):
        a, e = start[b], start[b + 1]
        for k in range(a + 1, e):
            v = order[k]
            kv = cell_key(cell_of(x[v], lower, inv_cell, dims), dims)
            m = k - 1
            while m >= a:
                u = order[m]
                ku = cell_key(cell_of(x[u], lower, inv_cell, dims), dims)
                if ku < kv or (ku == kv and u < v):
                    break
                order[m + 1] = u
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
    ps: TEMPLATE, h: ti.f32, q: TEMPLATE, scan: TEMPLATE, task: TEMPLATE, args: TEMPLATE,
    every_candidate: TEMPLATE, stop: TEMPLATE = None,
):
    """The one neighbour query: calls ``task(g, s, r², *args)`` for every
    particle within ``h`` of the point ``ps[g]`` (|x_s − ps[g]|² < h²), where
    ``ps`` is a list of points fixed at compile time (usually one), ``s`` is the
    particle's slot in cell order (``order[s]`` its index, ``x_sorted[s]`` its
    position) and r² its squared distance. ``q`` (a :data:`GridQuery`: ``lower``, ``inv_cell``,
    ``dims``, ``x_sorted``, ``start``) and ``scan`` (a :class:`Scan`: the reach and the table's
    layout) are those of a built :class:`NeighborGrid`, as :meth:`~NeighborGrid.query_args`
    gives them (a kernel takes ``q`` as one argument and hands it on as a template: it is not
    copied, which keeps the scan as fast as if it were written in the kernel). The solver's
    recorded launches (compute graphs take no argument packs) take the five as loose arguments
    and hand on a :class:`LooseQuery` of them instead.
    A point p falls in cell floor((p − lower)·inv_cell), clamped to [0, dims).
    ``args`` is a tuple handed on to ``task``; give its accumulators a
    ``ti.template()`` annotation in ``task`` so that they are updated in place.
    With ``every_candidate`` set (compile time), ``task`` is called for every
    candidate in the scanned cells, r² ≥ h² included, and tests r² itself: a
    task that can do so without a branch avoids mispredicting it (see
    :func:`_build_lists`). In a hashed grid the particles of other cells that share a
    scanned bucket are handed in too, with r² = :data:`FAR2`.

    Several points are searched in one scan when they lie in the same (x, y)
    column of cells (the caller sees to it, as :func:`_build_lists` does): each candidate
    is then loaded once and tested against every point, and the loop overhead
    of the 25 column runs is shared. The scan covers the union of the points'
    cells along z, reach cells beyond the lowest and the highest; candidates
    that only the union adds are at least h from the point they are tested
    against, so they never pass r² < h².

    Cells are h/reach wide, so the search covers (2·reach + 1)³ cells; the cells
    along z of each (x, y) column are adjacent in the cell numbering (dense) or in
    the buckets (hashed), so one contiguous run of the sorted order covers them,
    read from memory in order (hashed: two where the buckets wrap round the table's end).
    The loop over x runs at run time (one copy of the column scan). In the two outer x slices
    (dx = ±reach) the corner columns (dy = ±reach) are left out when their
    nearest edge is at least h from every point in x-y, which happens about two
    times in three for a point spread evenly in its cell: with cells of h/2 that
    is about 11 % of the candidates, and building the solver's lists took
    about 10 % less time (measured at 115k particles).

    With ``stop`` (compile time: a function of ``*args`` returning whether the
    query has learnt enough, or None), the nine nearest columns are scanned nearest
    first (:func:`nearest_columns`), then each further ring of them, with the same corner test; ``stop(*args)`` is asked
    before each: once it holds, the rest are skipped. Only a task whose result
    does not depend on the order it meets the candidates in can use it (a count
    that need only be known up to a threshold: :func:`~whitecap.diffuse.kernels.fluid_count`)."""
    reach = ti.static(scan.reach)
    cs = [cell_of(ps[g], q.lower, q.inv_cell, q.dims) for g in ti.static(range(len(ps)))]
    c = cs[0]
    z_lo = c.z
    z_hi = c.z
    for g in ti.static(range(1, len(ps))):
        z_lo = ti.min(z_lo, cs[g].z)
        z_hi = ti.max(z_hi, cs[g].z)
    z0 = ti.max(z_lo - reach, 0)
    z1 = ti.min(z_hi + reach, q.dims.z - 1)
    h2 = h * h
    w = 1.0 / q.inv_cell  # cell width
    # Corner test with h grown by a hundredth of a cell, so that rounding in f never drops a column holding a neighbour.
    h_corner2 = (h + CORNER_SLACK * w) ** 2
    if ti.static(_no_stop(stop)):
        # A loop at run time over x (LLVM unrolls its 2·reach + 1 steps): one copy of the column scan in the
        # kernel's source, not 2·reach + 1, which is what Taichi's front end takes its time over.
        for dx in range(-reach, reach + 1):
            cx = c.x + dx
            if 0 <= cx < q.dims.x:
                y0 = c.y - reach
                y1 = c.y + reach
                if dx == reach or dx == -reach:
                    y0 += _corner_beyond(ps, cs, q.lower, w, dx, -reach, reach, h_corner2)
                    y1 -= _corner_beyond(ps, cs, q.lower, w, dx, reach, reach, h_corner2)
                for cy in range(ti.max(y0, 0), ti.min(y1, q.dims.y - 1) + 1):
                    _scan_column(ps, cx, cy, z0, z1, q.lower, q.inv_cell, q.dims, q.x_sorted, q.start, scan, h2,
                                 task, args, every_candidate)
    else:
        # The nine nearest columns unrolled, nearest first (most queries stop among them); each further ring
        # of columns (|dx| or |dy| = k > 1) a loop at run time round it: one copy of the column scan for all
        # of them (unrolled, the 25 copies made fluid_count's kernel the slowest of all to compile).
        for d in ti.static([d for d in nearest_columns(reach) if max(abs(d[0]), abs(d[1])) <= 1]):
            if not stop(*args):
                _stop_column(ps, cs, c.x + d[0], c.y + d[1], d[0], d[1], z0, z1, q, scan, h2, w, h_corner2, task,
                             args, every_candidate)
        for k in ti.static(range(2, reach + 1)):
            for t in range(8 * k):  # the ring's columns: its sides along y at dx = ∓k, then along x at dy = ∓k
                side = t // (2 * k + 1)
                along = t % (2 * k + 1) - k
                dx = ti.select(side == 0, -k, ti.select(side == 1, k, 0))
                dy = along
                if t >= 2 * (2 * k + 1):  # the rest of the ring: dy = ∓k, dx from −k + 1 to k − 1
                    u = t - 2 * (2 * k + 1)
                    dx = u % (2 * k - 1) - (k - 1)
                    dy = ti.select(u < 2 * k - 1, -k, k)
                if not stop(*args):
                    _stop_column(ps, cs, c.x + dx, c.y + dy, dx, dy, z0, z1, q, scan, h2, w, h_corner2, task, args,
                                 every_candidate)


@ti.func
def _stop_column(
    ps: TEMPLATE, cs: TEMPLATE, cx, cy, dx, dy, z0, z1, q: TEMPLATE, scan: TEMPLATE, h2, w, h_corner2, task: TEMPLATE,
    args: TEMPLATE, every_candidate: TEMPLATE,
):
    """Column (cx, cy) = the query's cell + (dx, dy) of a query with a ``stop`` (:func:`for_each_neighbor`), where
    it lies in the grid and, at a corner of the scan, unless beyond h from every point."""
    reach = ti.static(scan.reach)
    go = ti.cast((0 <= cx) & (cx < q.dims.x) & (0 <= cy) & (cy < q.dims.y), ti.i32)
    if (dx == reach or dx == -reach) and (dy == reach or dy == -reach):
        go = go * (1 - _corner_beyond(ps, cs, q.lower, w, dx, dy, reach, h_corner2))
    if go:
        _scan_column(ps, cx, cy, z0, z1, q.lower, q.inv_cell, q.dims, q.x_sorted, q.start, scan, h2, task, args,
                     every_candidate)


def _no_stop(stop) -> bool:
    """Whether a query has no ``stop`` (a Python test: Taichi's scope has no ``is``)."""
    return stop is None


def nearest_columns(reach: int) -> list[tuple[int, int]]:
    """The (dx, dy) offsets of the (2·reach + 1)² columns a query scans, nearest first (by dx² + dy², then
    dx, dy): the order of a query with a ``stop`` (:func:`for_each_neighbor`)."""
    cols = [(dx, dy) for dx in range(-reach, reach + 1) for dy in range(-reach, reach + 1)]
    return sorted(cols, key=lambda d: (d[0] * d[0] + d[1] * d[1], d[0], d[1]))


@ti.func
def _corner_beyond(ps: TEMPLATE, cs: TEMPLATE, lower: TEMPLATE, w, dx, dy, reach: TEMPLATE, h_corner2) -> ti.i32:
    """1 if corner column (dx, dy) of the scan (|dx| = reach; dy = ±reach) can be left out: its nearest edge is at
    least h (grown by CORNER_SLACK cells: h_corner2) from every point ``ps[g]`` (in cell ``cs[g]``) in x-y."""
    beyond = 1
    for g in ti.static(range(len(ps))):
        f = ps[g] - (lower + ti.cast(cs[g], ti.f32) * w)  # the point's offset inside its cell
        ex = ti.select(dx > 0, dx * w - f.x, (-dx - 1) * w + f.x)
        ey = ti.select(dy > 0, reach * w - f.y, (reach - 1) * w + f.y)
        if ex * ex + ey * ey < h_corner2:
            beyond = 0
    return beyond


@ti.func
def _scan_column(
    ps: TEMPLATE, cx, cy, z0, z1, lower: TEMPLATE, inv_cell: TEMPLATE, dims: TEMPLATE, x_sorted: F3,
    start: I1, scan: TEMPLATE, h2, task: TEMPLATE, args: TEMPLATE, every_candidate: TEMPLATE,
):
    """The cells z0..z1 of column (cx, cy), every candidate offered to ``task`` (see :func:`for_each_neighbor`)."""
    if ti.static(scan.hashed):
        _scan_hashed_column(ps, cx, cy, z0, z1, lower, inv_cell, dims, x_sorted, start, h2, task, args,
                            every_candidate)
    else:
        first = start[cell_index(ivec3(cx, cy, z0), dims)]
        last = start[cell_index(ivec3(cx, cy, z1), dims) + 1]
        for s in range(first, last):
            q = x_sorted[s]
            for g in ti.static(range(len(ps))):
                _offer(g, s, (q - ps[g]).norm_sqr(), h2, task, args, every_candidate)


@ti.func
def _offer(g: TEMPLATE, s, r2, h2, task: TEMPLATE, args: TEMPLATE, every_candidate: TEMPLATE):
    """Hands candidate slot ``s`` at squared distance r² from point g to ``task`` (see :func:`for_each_neighbor`)."""
    if ti.static(every_candidate):
        task(g, s, r2, *args)
    elif r2 < h2:
        task(g, s, r2, *args)


@ti.func
def _scan_hashed_column(
    ps: TEMPLATE, cx, cy, z0, z1, lower: TEMPLATE, inv_cell: TEMPLATE, dims: TEMPLATE, x_sorted: F3,
    start: I1, h2, task: TEMPLATE, args: TEMPLATE, every_candidate: TEMPLATE,
):
    """The cells z0..z1 of column (cx, cy) of a hashed grid: buckets (H + z0) .. (H + z1) mod T, one run
    of the sorted order (where they wrap round the table's end, its tail and then its head). A particle
    is offered at its true distance when its own cell is one of these (tested on its position, exactly as
    cell_of computes the cell), else at r² = FAR2: the run also holds the particles of other cells that
    share these buckets, each of which is met, and taken, only through its own cell."""
    mask = start.shape[0] - 2  # T − 1: start has T + 1 entries
    b0 = bucket_of(ivec3(cx, cy, z0), mask)
    b1 = bucket_of(ivec3(cx, cy, z1), mask)
    n = start[mask + 1]  # the particles sorted
    first = start[b0]
    last = start[b1 + 1]
    if b1 < b0:  # wrapped round the table's end: slots n.. stand for 0..
        last += n
    # The cells' bounds in units of cells, open where a border cell takes the points beyond it:
    # floor(clamp(f, 0, dims − 1)) of cell_of lies in [lo, hi) exactly when f does (the bounds are whole).
    lo = ti.cast(ivec3(cx, cy, z0), ti.f32)
    hi = ti.cast(ivec3(cx, cy, z1) + 1, ti.f32)
    far = ti.cast(FAR2, ti.f32)
    lo = ti.select(ivec3(cx, cy, z0) == 0, -far, lo)
    hi = ti.select(ivec3(cx, cy, z1) == dims - 1, far, hi)
    for t in range(first, last):
        s = ti.select(t >= n, t - n, t)
        q = x_sorted[s]
        f = (q - lower) * inv_cell  # as in cell_of
        mine = (f.x >= lo.x) & (f.x < hi.x) & (f.y >= lo.y) & (f.y < hi.y) & (f.z >= lo.z) & (f.z < hi.z)
        for g in ti.static(range(len(ps))):
            _offer(g, s, ti.select(mine, (q - ps[g]).norm_sqr(), FAR2), h2, task, args, every_candidate)


#: Particles of one column of cells whose neighbour lists are built in one scan
#: on the CPU, and how many cells apart along z they may lie for it.
#: Measured at 115k particles after 80 steps (Xeon, 2 cores; the same lists),
#: min of 12 builds in two rounds, groups of consecutive slots: one by one
#: 30.1 / 30.4 ms, groups of 2 19.8 / 19.9, 3 22.4 / 21.7, 4 18.2 / 17.5
#: (spread 8; 18.6 / 20.5 with 4, 18.3 / 19.0 with 6), 5 20.0 / 20.0, 6
#: 20.6 / 20.0. Groups aligned to the columns (_build_lists): 17.4–17.9 →
#: 16.5–16.8 ms there, and 3.0 → 2.2 ms on frame 20 of the bunny demo.
GROUP = 4
GROUP_SPREAD = 8
#: The marked particles of a group at least, for a marked build (_build_marked_lists) to scan the group at once;
#: fewer, each is scanned alone. The foam stage marks a few per cent of the particles, mostly one in a group:
#: scanning its group made four lists where one was wanted. On bench_foam's 98k sequence (2 cores, Python's
#: clock round the launches): the builds of its 10 frames took 28-30 ms with 2, 31-33 with each marked particle
#: alone, 37 when any one marked made the group's scan; the calibration's (3 frames, a fifth of the particles
#: marked, in runs of 64 slots) 32-36 ms with 2, 43-44 alone, 40 with any one.
MARKED_GROUP = 2
#: Neighbour rows are padded to a multiple of this many entries on a CPU whose
#: vector gathers LLVM uses (:func:`cpu_gathers`): the 8 single-precision lanes
#: that it vectorises the solver's neighbour loops with. Measured on λ at 115k
#: particles: Intel Xeon with AVX-512, 5.00 → 4.05 ms a pass; AMD EPYC (no
#: gathers: vectors built from scalar loads), 4.1 → 4.4 ms, so 1 there. On a
#: GPU each particle has its own thread and padding would only add work: 1.
LIST_PAD = 8


@functools.lru_cache(maxsize=1)
def cpu_gathers() -> bool:
    """Whether LLVM vectorises gathered loads with gather instructions on this processor:
    x86-64 with AVX-512, or Intel's with AVX2 (LLVM 15's x86 cost model; AMD's before
    AVX-512 build vectors from scalar loads). Read from /proc/cpuinfo; False elsewhere."""
    try:
        with open("/proc/cpuinfo") as fh:
            info: dict[str, str] = {}
            for line in fh:
                key, _, value = line.partition(":")
                info.setdefault(key.strip(), value.strip())
                if "flags" in info and "vendor_id" in info:
                    break
    except OSError:
        return False
    flags = set(info.get("flags", "").split())
    return "avx512f" in flags or (info.get("vendor_id") == "GenuineIntel" and "avx2" in flags)


@ti.func
def _within_spread(cs: TEMPLATE, spread: TEMPLATE) -> ti.i32:
    """1 if the cells ``cs`` (of one column) lie at most ``spread`` cells apart along z."""
    z_lo = cs[0].z
    z_hi = cs[0].z
    for g in ti.static(range(1, len(cs))):
        z_lo = ti.min(z_lo, cs[g].z)
        z_hi = ti.max(z_hi, cs[g].z)
    return z_hi - z_lo <= spread


@ti.func
def _append_slot(
    g: TEMPLATE, s, r2, slots: TEMPLATE, h2, bufs: TEMPLATE, cap: TEMPLATE, ks: TEMPLATE
):
    """Branch-free append of candidate slot ``s`` to the local list ``bufs[g]`` of the
    particle in slot ``slots[g]``: the slot is always written at ``ks[g]`` (at ``cap``,
    a sink, once the list is full) and ``ks[g]`` advances only when the candidate is
    within h (r² < h²) and is not the particle itself. ``ks[g]`` keeps counting past
    ``cap``: the excess is the overflow."""
    bufs[g][ti.min(ks[g], cap)] = s
    ks[g] += ti.select((r2 < h2) & (s != slots[g]), 1, 0)


@ti.kernel
def _build_lists(
    n: ti.i32, lower: vec3, inv_cell: ti.f32, dims: ivec3, x_sorted: F3, start: I1, scan: TEMPLATE, h: ti.f32,
    order: I1, nb_count: I1, nb: I2, cap: TEMPLATE, overflow: I1, pad: TEMPLATE, group: TEMPLATE,
):
    """Fills nb[i, :nb_count[i]] with the neighbours of every particle i, in the
    order :func:`for_each_neighbor` meets them, and the rest of the row up to a
    multiple of ``pad`` (at most ``cap``) with i itself (see :func:`_store_list`);
    adds how many did not fit to ``overflow[0]``.

    On the CPU the particles of each column of cells are taken ``group``
    (:data:`GROUP`) at a time, in cell order from the column's first: the
    particle that starts a group (its slot minus the column's first slot is a
    multiple of ``group``) builds the lists of the group, the others skip. A
    group that lies within :data:`GROUP_SPREAD` cells along z is searched in
    one scan, the others one by one; the lists are the same either way.
    Groups never span two columns, which matters where columns are short
    (thin water, spray: in the bunny demo 38–49 % of the groups of four
    consecutive slots spanned two columns), and the loop stays one over the
    particles, so the two threads share it evenly. On a GPU (``group`` 1)
    every particle builds its own list.

    Every candidate is handled without a branch on its distance
    (:func:`_append_slot`), into a list local to the thread (``cap`` + 1 slots
    on the stack), which is then copied out: once the starting lattice has
    disordered, about a third of the ~115 candidates a particle are neighbours,
    in no pattern the processor can predict, and the branch per candidate made
    this kernel 2.4× slower than on the lattice. Measured at 115k particles:
    16 → 20 ms on the lattice (step 5), 40 → 27 ms at step 70. Stores into the
    local list, unlike stores into ``nb``, cannot alias the grid arrays, so
    their loads stay hoisted out of the candidate loop."""
    for si in range(n):
        # Walk particles in cell order: consecutive ones share their
        # candidate cells, which then stay in cache.
        _lists_at(si, n, lower, inv_cell, dims, x_sorted, start, scan, h, order, nb_count, nb, cap, overflow, pad,
                  group, order, 0, False)


@ti.kernel
def _build_marked_lists(
    n: ti.i32, lower: vec3, inv_cell: ti.f32, dims: ivec3, x_sorted: F3, start: I1, scan: TEMPLATE, h: ti.f32,
    order: I1, nb_count: I1, nb: I2, cap: TEMPLATE, overflow: I1, pad: TEMPLATE, group: TEMPLATE, mark: I1,
    value: ti.i32,
):
    """:func:`_build_lists` for the particles i with mark[i] == ``value`` only (the rows of the others are left
    as they were, but those of a group built in one scan): a group is scanned at once where MARKED_GROUP of its
    particles are marked, else each marked one alone; a list is the same either way (the lists do not depend on
    the grouping)."""
    for si in range(n):
        _lists_at(si, n, lower, inv_cell, dims, x_sorted, start, scan, h, order, nb_count, nb, cap, overflow, pad,
                  group, mark, value, True)


@ti.func
def _lists_at(
    si, n, lower: TEMPLATE, inv_cell: TEMPLATE, dims: TEMPLATE, x_sorted: F3, start: I1, scan: TEMPLATE, h,
    order: I1, nb_count: I1, nb: I2, cap: TEMPLATE, overflow: I1, pad: TEMPLATE, group: TEMPLATE, mark: I1,
    value, marked: TEMPLATE,
):
    """The lists slot ``si`` builds (see :func:`_build_lists`): its own (``group`` 1) or its group's when it
    leads one. With ``marked`` (compile time), only those of particles with mark[order[slot]] == value: the
    group's in one scan where MARKED_GROUP of them are, else each marked one's alone."""
    h2 = h * h
    if ti.static(group == 1):
        if ti.static(not marked):
            _single_list(si, h, h2, lower, inv_cell, dims, x_sorted, start, scan, order, nb_count, nb, cap, overflow,
                         pad)
        elif mark[order[si]] == value:
            _single_list(si, h, h2, lower, inv_cell, dims, x_sorted, start, scan, order, nb_count, nb, cap, overflow,
                         pad)
    else:
        c0 = cell_of(x_sorted[si], lower, inv_cell, dims)
        lead = 0
        end = n  # one past the last slot a group may take
        if ti.static(scan.hashed):
            lead = ti.cast(si % group == 0, ti.i32)  # groups of consecutive slots; one column or one by one
        else:
            column = (c0.x * dims.y + c0.y) * dims.z  # the column's first cell
            lead = ti.cast((si - start[column]) % group == 0, ti.i32)
            end = start[column + dims.z]  # one past the column's last slot
        some = group  # marked particles in the group
        if ti.static(marked):
            if lead:
                some = 0
                for g in ti.static(range(group)):
                    some += ti.cast(si + g < end, ti.i32) & ti.cast(mark[order[ti.min(si + g, end - 1)]] == value,
                                                                     ti.i32)
                if 0 < some < MARKED_GROUP:
                    lead = 0
                    for g in range(group):  # a loop: one more copy of the scan's code, not four
                        if si + g < end:
                            if mark[order[si + g]] == value:
                                _single_list(si + g, h, h2, lower, inv_cell, dims, x_sorted, start, scan, order,
                                             nb_count, nb, cap, overflow, pad)
        if lead and some > 0:
            slots = [ti.min(si + g, end - 1) for g in ti.static(range(group))]
            ps = [x_sorted[slots[g]] for g in ti.static(range(group))]
            cs = [cell_of(ps[g], lower, inv_cell, dims) for g in ti.static(range(group))]
            together = _within_spread(cs, GROUP_SPREAD)
            if ti.static(scan.hashed):
                together &= _one_column(cs)
            if together:
                bufs = [ti.Vector([0] * (cap + 1), dt=ti.i32) for _ in ti.static(range(group))]  # [cap]: sink
                ks = [0 for _ in ti.static(range(group))]
                q = ti.static(LooseQuery(lower, inv_cell, dims, x_sorted, start))
                for_each_neighbor(ps, h, q, scan, _append_slot, (slots, h2, bufs, cap, ks), True)
                for g in ti.static(range(group)):
                    if si + g < end:
                        _store_list(order, slots[g], bufs[g], ks[g], cap, nb_count, nb, overflow, pad)
            else:
                for g in range(group):  # one by one (a loop: one more copy of the scan's code, not four)
                    if si + g < end:
                        _single_list(si + g, h, h2, lower, inv_cell, dims, x_sorted, start, scan, order,
                                     nb_count, nb, cap, overflow, pad)


@ti.func
def _one_column(cs: TEMPLATE) -> ti.i32:
    """1 if the cells ``cs`` lie in one (x, y) column."""
    same = 1
    for g in ti.static(range(1, len(cs))):
        same &= ti.cast((cs[g].x == cs[0].x) & (cs[g].y == cs[0].y), ti.i32)
    return same


@ti.func
def _single_list(
    si, h, h2, lower: TEMPLATE, inv_cell: TEMPLATE, dims: TEMPLATE, x_sorted: F3, start: I1,
    scan: TEMPLATE, order: I1, nb_count: I1, nb: I2, cap: TEMPLATE, overflow: I1, pad: TEMPLATE,
):
    """The neighbour list of the particle in slot ``si`` alone (see :func:`_build_lists`)."""
    buf = ti.Vector([0] * (cap + 1), dt=ti.i32)  # buf[cap]: the sink of the overflow
    k = 0
    q = ti.static(LooseQuery(lower, inv_cell, dims, x_sorted, start))
    for_each_neighbor([x_sorted[si]], h, q, scan, _append_slot, ([si], h2, [buf], cap, [k]), True)
    _store_list(order, si, buf, k, cap, nb_count, nb, overflow, pad)


@ti.func
def _store_list(
    order: I1, si, buf: TEMPLATE, k, cap: TEMPLATE, nb_count: I1, nb: I2, overflow: I1, pad: TEMPLATE
):
    """Copies the local list ``buf`` (``k`` candidates counted, at most ``cap`` kept) of the particle
    in slot ``si`` out to its row of ``nb``, as particle indices; counts the excess as overflow.

    The row is then padded with the particle itself up to a multiple of ``pad``
    (:data:`LIST_PAD` on a CPU with gathers), where the solver's neighbour loops read it
    (:func:`~whitecap.sim.pbf.padded_count`): LLVM vectorises those loops ``pad``
    neighbours at a time and leaves the rest of a list to a scalar loop, about
    a fifth of the pass for the usual 25–35 neighbours. A pair of a particle with
    itself adds exactly nothing to their sums (∇W(0) = 0, v_i − v_i = 0; λ's
    density sum skips it). ``nb_count`` stays the true count."""
    i = order[si]
    m = ti.min(k, cap)
    for q in range(m):
        nb[i, q] = order[buf[q]]
    if ti.static(pad > 1):
        for q in range(m, ti.min((m + pad - 1) // pad * pad, cap)):
            nb[i, q] = i
    nb_count[i] = m
    if k > m:
        ti.atomic_add(overflow[0], k - m)


@dataclass
class GridSpec:
    lower: tuple[float, float, float]
    cell: float
    dims: tuple[int, int, int]

    @property
    def ncells(self) -> int:
        return self.dims[0] * self.dims[1] * self.dims[2]


def grid_spec(lower, upper, cell: float) -> GridSpec:
    """Cells of width ``cell`` over the box [lower, upper]. Any number of cells is allowed (a hashed
    table holds only the occupied ones), up to :data:`MAX_AXIS_CELLS` along an axis."""
    dims = tuple(max(1, int(math.ceil((u - lo) / cell))) for lo, u in zip(lower, upper))
    if max(dims) > MAX_AXIS_CELLS:
        raise WhitecapError(
            f"neighbour grid of {dims} cells has more than {MAX_AXIS_CELLS} along an axis; "
            "the domain is huge compared with the kernel support"
        )
    return GridSpec(tuple(float(v) for v in lower), float(cell), dims)  # type: ignore[arg-type]


def grid_layout(spec: GridSpec, capacity: int) -> str:
    """'dense' while the domain has at most :data:`DENSE_CELLS_PER_PARTICLE` cells per particle of
    capacity (or :data:`DENSE_ALWAYS_CELLS` cells) and its cells are numbered in i32; else 'hashed'."""
    nc = spec.ncells
    if nc <= max(DENSE_CELLS_PER_PARTICLE * int(capacity), DENSE_ALWAYS_CELLS) and nc < 2**31 - 1:
        return "dense"
    return "hashed"


def hash_buckets(capacity: int, per_particle: int | None = None) -> int:
    """Buckets of a hashed table: the power of two at or above BUCKETS_PER_PARTICLE × capacity."""
    want = max((BUCKETS_PER_PARTICLE if per_particle is None else per_particle) * int(capacity), MIN_BUCKETS)
    return 1 << (want - 1).bit_length()


#: Elements an ndarray may hold: Taichi 1.7 indexes them with 32-bit integers (it warns, and the allocation of
#: 50 M particles' lists of 64 failed on an H100 with 80 GB).
MAX_NDARRAY_ELEMENTS = 2**31 - 1
#: Fewest slots a neighbour list may be cut to for that limit (PBF's particles have 25-35 neighbours at rest).
MIN_LIST_SLOTS = 32


def list_slots(capacity: int, max_neighbors: int) -> int:
    """Slots of a particle's neighbour list: ``max_neighbors``, or as many as keep the lists of ``capacity``
    particles within MAX_NDARRAY_ELEMENTS (42 at 50 M particles); WhitecapError below MIN_LIST_SLOTS."""
    fit = MAX_NDARRAY_ELEMENTS // max(int(capacity), 1)
    if fit >= max_neighbors:
        return int(max_neighbors)
    if fit < MIN_LIST_SLOTS:
        raise WhitecapError(
            f"{capacity:,} particles: their neighbour lists would hold {fit} entries each (Taichi indexes an "
            f"array with 32-bit integers, {MAX_NDARRAY_ELEMENTS:,} entries in all), under the {MIN_LIST_SLOTS} "
            "that PBF needs; use fewer particles (a larger particle_radius)"
        )
    return fit


class NeighborGrid:
    """Cell-sorted particle order plus fixed-capacity neighbour lists.

    After :meth:`build`, ``order[start[c]:start[c+1]]`` are the particles in
    table entry ``c`` (a cell of the domain in the dense layout, a bucket in the
    hashed one) and ``nb[i, :nb_count[i]]`` the neighbours of particle ``i``
    within ``h`` (excluding ``i`` itself). Kernels query the grid around any
    point with :func:`for_each_neighbor` and :meth:`query_args`. ``layout``:
    'dense', 'hashed' or 'auto' (:func:`grid_layout`).
    """

    def __init__(self, spec: GridSpec, capacity: int, max_neighbors: int, h: float, layout: str = "auto"):
        self.spec = spec
        # Cells of h/2 test ~125/216 as many candidates as cells of h (measured
        # ~25 % faster list building); coarser cells are searched with reach 1.
        self.reach = max(1, int(round(h / spec.cell)))
        self.h = float(h)
        self.capacity = int(capacity)
        self.max_neighbors = list_slots(self.capacity, max_neighbors)  # pairs past it: counted in overflow
        self.cut = self.max_neighbors < max_neighbors  # the lists are shorter than asked, for 32-bit indices
        if self.cut:
            from ..progress import console

            console.print(
                f"[yellow]note:[/] neighbour lists of {self.max_neighbors} entries a particle at {self.capacity:,} "
                f"particles, not {max_neighbors} (Taichi indexes an array with 32-bit integers); pairs past them "
                "are counted and left out", soft_wrap=True,
            )
        if layout == "auto":
            layout = grid_layout(spec, self.capacity)
        if layout not in ("dense", "hashed"):
            raise ValueError(f"grid layout {layout!r}: expected 'dense', 'hashed' or 'auto'")
        self.layout = layout
        self.hashed = layout == "hashed"
        self.scan = Scan(self.reach, self.hashed)
        # Particles a scan (_build_lists) and rows padded to a multiple of (_store_list): both measured on
        # the CPU only; a GPU runs a thread per particle, as before.
        cpu = not runtime.on_gpu()
        self.group = GROUP if cpu else 1
        self.pad = LIST_PAD if cpu and cpu_gathers() else 1
        nc = self.table_size = hash_buckets(capacity) if self.hashed else spec.ncells
        self.cell = ti.ndarray(ti.i32, capacity)
        self.rank = ti.ndarray(ti.i32, capacity)
        self.order = ti.ndarray(ti.i32, capacity)
        self.start = ti.ndarray(ti.i32, nc + 1)  # the counts while sorting, then each entry's first slot
        self.bsum = ti.ndarray(ti.i32, len_blocks(nc))
        grouped = not cpu if GROUPED_SCAN is None else GROUPED_SCAN
        self.sum_group = SCAN_GROUP_GPU if grouped else 0  # the block sums scanned in groups (_scan_blocks)
        self.gsum = ti.ndarray(ti.i32, len_groups(nc, self.sum_group) if grouped else 1)
        self.nb_count = ti.ndarray(ti.i32, capacity)
        # a row is read up to its written count
        self.nb = runtime.empty_ndarray(ti.i32, (capacity, self.max_neighbors))
        self.x_sorted = ti.Vector.ndarray(3, ti.f32, capacity)
        self.overflow_count = ti.ndarray(ti.i32, 1)  # pairs that did not fit, added up by _build_lists
        self.overflow_count.fill(0)
        self.overflow = 0
        self.lower = vec3(*spec.lower)
        self.inv_cell = 1.0 / spec.cell
        self.dims = ivec3(*spec.dims)
        self.query = GridQuery(
            lower=self.lower, inv_cell=self.inv_cell, dims=self.dims, x_sorted=self.x_sorted, start=self.start
        )

    def nbytes(self) -> int:
        nc = self.table_size
        return 4 * (self.capacity * (7 + self.max_neighbors) + nc + 1 + len_blocks(nc) + self.gsum.shape[0] + 1)

    def bindings(self) -> dict:
        """The grid's arrays and constants by the names its recorded launches use (``g.*``;
        ``g.ncells``: the entries of the cell table, cells or buckets)."""
        return {
            "g.cell": self.cell, "g.rank": self.rank, "g.order": self.order, "g.start": self.start,
            "g.bsum": self.bsum, "g.gsum": self.gsum, "g.nb_count": self.nb_count, "g.nb": self.nb,
            "g.x_sorted": self.x_sorted, "g.overflow": self.overflow_count, "g.lower": self.lower,
            "g.inv_cell": self.inv_cell, "g.dims": self.dims, "g.ncells": self.table_size, "g.h": self.h,
        }

    def record_sort(self, rec, x, n) -> None:
        """Counting sort of the first ``n`` positions of ``x`` into cells (``x``, ``n``: Refs)."""
        rec(_clear, rec["g.start"], rec["g.ncells"])
        count = _count_buckets if self.hashed else _count_cells
        rec(count, n, x, rec["g.lower"], rec["g.inv_cell"], rec["g.dims"], rec["g.cell"], rec["g.rank"],
            rec["g.start"])
        rec(_block_sums, rec["g.start"], rec["g.ncells"], rec["g.bsum"])
        rec(_scan_blocks, rec["g.bsum"], rec["g.gsum"], self.sum_group)
        rec(_scan_cells, rec["g.start"], rec["g.ncells"], rec["g.bsum"], rec["g.gsum"], n, self.sum_group)
        rec(_scatter, n, rec["g.cell"], rec["g.rank"], rec["g.start"], rec["g.order"])
        if self.hashed:
            rec(_sort_buckets, rec["g.ncells"], rec["g.start"], rec["g.order"], x, rec["g.lower"],
                rec["g.inv_cell"], rec["g.dims"])
        else:
            rec(_sort_cells, rec["g.ncells"], rec["g.start"], rec["g.order"])

    def record_build(self, rec, x, n, lists: bool = True) -> None:
        """Sort, then fill the neighbour lists (unless not ``lists``: then only the sort and the positions in
        cell order, all that :func:`for_each_neighbor` reads); overflowing pairs are added to ``overflow_count``."""
        self.record_sort(rec, x, n)
        rec(gather_vec3, n, rec["g.order"], x, rec["g.x_sorted"])
        if not lists:
            return
        rec(
            _build_lists, n, rec["g.lower"], rec["g.inv_cell"], rec["g.dims"], rec["g.x_sorted"], rec["g.start"],
            self.scan, rec["g.h"], rec["g.order"], rec["g.nb_count"], rec["g.nb"], self.max_neighbors,
            rec["g.overflow"], self.pad, self.group,
        )

    def sort(self, x, n: int) -> None:
        """Counting sort of the first ``n`` positions of ``x`` into cells."""
        run_direct(lambda rec: self.record_sort(rec, rec["x"], rec["n"]), {**self.bindings(), "x": x, "n": n})

    def build(self, x, n: int, lists: bool = True) -> int:
        """Sort and fill neighbour lists; returns how many neighbours overflowed. Without ``lists``, only
        the sort and the positions in cell order (for queries with :func:`for_each_neighbor`; ``nb`` and
        ``nb_count`` are left as they were); returns 0."""
        if not lists:
            run_direct(lambda rec: self.record_build(rec, rec["x"], rec["n"], False),
                       {**self.bindings(), "x": x, "n": n})
            self.overflow = 0
            return 0
        before = int(self.overflow_count[0])  # what recorded steps counted and no one took yet stays
        run_direct(lambda rec: self.record_build(rec, rec["x"], rec["n"]), {**self.bindings(), "x": x, "n": n})
        self.overflow = int(self.overflow_count[0]) - before
        return self.overflow

    def build_sorted(self, x, n: int, v, v_sorted) -> None:
        """:meth:`build` without lists, and ``v_sorted[s] = v[order[s]]``: a second array (the velocities) in cell
        order, as the queries meet the particles. Ten launches, as one Taichi compute graph where the backend has
        them: launched from C++, each costs about 55 µs less than from Python (the foam stage's sort of a 98k
        frame, 2 cores: 2.2 against 1.65 ms)."""
        global _GRAPHS_REFUSED
        bindings = {**self.bindings(), "x": x, "n": n, "v": v, "vs": v_sorted}
        key = (self.hashed, self.sum_group)  # what the graph compiles in (templates); the arrays are arguments
        graph = _SORTED_GRAPHS.get(key)
        if graph is None and not _GRAPHS_REFUSED:
            try:  # once a process for each table layout: the graph takes every array as an argument
                graph = _SORTED_GRAPHS[key] = KernelGraph(self._record_sorted)
            except Exception:  # a backend without compute graphs: the same launches one by one
                _GRAPHS_REFUSED = True
        if graph is not None:
            graph.run(bindings)
        else:
            run_direct(self._record_sorted, bindings)
        self.overflow = 0

    def _record_sorted(self, rec) -> None:
        self.record_build(rec, rec["x"], rec["n"], False)
        rec(gather_vec3, rec["n"], rec["g.order"], rec["v"], rec["vs"])

    def build_marked(self, n: int, mark, value: int) -> None:
        """After :meth:`build` without lists: the neighbour lists of the particles i with mark[i] == ``value``
        (and of the others of their groups), the same rows a whole build makes; the other rows are left as
        they were. Overflowing pairs are added to ``overflow_count`` (a row built twice counts twice)."""
        _build_marked_lists(n, self.lower, self.inv_cell, self.dims, self.x_sorted, self.start, self.scan, self.h,
                            self.order, self.nb_count, self.nb, self.max_neighbors, self.overflow_count, self.pad,
                            self.group, mark, value)

    def take_overflow(self) -> int:
        """Neighbour pairs that did not fit since the last call (reads back from the device)."""
        k = int(self.overflow_count[0])
        if k:
            self.overflow_count.fill(0)
        return k

    def query_args(self) -> tuple:
        """(query, scan): what a kernel hands :func:`for_each_neighbor` to search this grid after
        :meth:`build`: ``query`` a :data:`GridQuery` (made once with the grid), ``scan`` a :class:`Scan`,
        a compile-time template (the reach and the table's layout)."""
        return self.query, self.scan


#: build_sorted's compute graph for each table layout (hashed or not), made at its first call in the process
_SORTED_GRAPHS: dict[tuple[bool, int], KernelGraph] = {}  # by (hashed, sum_group)
_GRAPHS_REFUSED = False  # the backend turned a compute graph down: build_sorted launches one by one


def len_blocks(nc: int) -> int:
    return (nc + SCAN_BLOCK - 1) // SCAN_BLOCK


def len_groups(nc: int, group: int) -> int:
    """Groups of ``group`` block sums of a table of ``nc`` entries (at least one: an array is never empty)."""
    return max(1, -(-len_blocks(nc) // group))
