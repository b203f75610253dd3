"""Reference writers the diffuse tests compare the generator against (not a test module).

:func:`generate` writes every candidate of a frame one fluid particle at a time, the plain order
that the generator's chunked, parallel-over-candidates kernels must reproduce bit for bit.
"""

import taichi as ti

from whitecap.diffuse.kernels import U1, clamp_phi, new_particle
from whitecap.sim.grid import F1, F3, I1


@ti.kernel
def generate(
    n: ti.i32,
    x: F3,
    v: F3,
    ids: U1,
    e_k: F1,
    tau: F1,
    count: I1,
    offset: I1,
    life_min: ti.f32,
    life_max: ti.f32,
    life_mult: ti.f32,
    r_v: ti.f32,
    dt: ti.f32,
    seed: ti.u32,
    frame: ti.u32,
    out_x: F3,
    out_v: F3,
    out_life: F1,
):
    """The count[i] new particles of fluid particle i (from kernels.birth_counts, see kernels.new_particle),
    in parallel over the fluid particles. Particle i writes only its own run [offset[i], offset[i] + count[i])
    (offset: the exclusive prefix sum of count), so the order is fixed whatever the thread count.
    kernels.generate_candidates writes the same particles, in parallel over them."""
    for i in range(n):
        i_k = clamp_phi(e_k[i], tau[4], tau[5])
        for s in range(count[i]):
            k = offset[i] + s
            out_x[k], out_v[k], out_life[k] = new_particle(x[i], v[i], ids[i], s, i_k, life_min, life_max, life_mult,
                                                           r_v, dt, seed, frame)
