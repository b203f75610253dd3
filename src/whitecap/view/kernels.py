"""Drawing kernels that run where the particles are (CPU or GPU).

No ``from __future__ import annotations`` here: Taichi reads the kernel
annotations as objects.
"""

import taichi as ti

from ..sim.grid import F1, F3
from .colors import COLORMAP_STOPS

# The stops as plain Python constants, so the kernel sees compile-time values
# (calling len() or .tolist() inside a kernel makes Taichi print a warning).
_N_STOPS = len(COLORMAP_STOPS)
_STOPS = tuple(tuple(float(c) for c in s) for s in COLORMAP_STOPS)


@ti.func
def _colormap(s, lo, hi):
    """The colour map of :func:`colors.colormap`, for one value inside a kernel."""
    t = ti.math.clamp((s - lo) / ti.max(hi - lo, 1e-12), 0.0, 1.0) * (_N_STOPS - 1)
    k = ti.min(ti.cast(t, ti.i32), _N_STOPS - 2)
    w = t - k
    c = ti.Vector([0.0, 0.0, 0.0])
    for j in ti.static(range(_N_STOPS - 1)):
        if k == j:
            c = (1.0 - w) * ti.Vector(_STOPS[j]) + w * ti.Vector(_STOPS[j + 1])
    return c


@ti.kernel
def fill_fluid_buffer(n: ti.i32, x: F3, v: F3, rho: F1, by_density: ti.i32, lo: ti.f32, hi: ti.f32,
                      pos: ti.template(), col: ti.template()):  # type: ignore[valid-type]  # taichi's, not a type
    """GGUI vertices of a live solver: positions x_i and the colour of |v_i| or ρ_i,
    written on the compute device (no copy through numpy, which dominated on a GPU)."""
    for i in range(n):
        pos[i] = x[i]
        s = v[i].norm()
        if by_density:
            s = rho[i]
        col[i] = _colormap(s, lo, hi)
